"""Evaluation: angular-error metrics, the ground-truth-free detail ratio, benchmark datasets."""
