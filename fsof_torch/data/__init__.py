"""Data: procedural driving scenes with exact ground truth, and datasets."""
