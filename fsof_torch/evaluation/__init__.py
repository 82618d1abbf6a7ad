"""Evaluation: backward warping, photometric error, ground-truth metrics and pictures."""
