"""The evaluation job (``python -m eval``): synthetic data, the paper's tables, training demo."""
