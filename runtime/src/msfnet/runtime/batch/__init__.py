"""Batches: many stacks through one loaded model, locally or on a Ray cluster."""
