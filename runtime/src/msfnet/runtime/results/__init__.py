"""Results of a run: the result files, the latency profile and the inspection maps."""
