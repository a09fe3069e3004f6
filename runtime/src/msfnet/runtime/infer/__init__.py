"""Inference: the network's normalisation, memory-bounded tiling, estimators (network, least
squares, fine detail) and the network's analytic cost."""
