"""Inspection: registered maps -> defect regions -> a verdict (``defects``), the warm per-part
station (``station``) and its watch loop over a folder of parts (``watch``)."""
