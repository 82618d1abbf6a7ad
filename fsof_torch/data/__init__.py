"""Data: procedural driving scenes with exact ground truth (``scene``), the one item contract of
every dataset (``items``), and the datasets (``datasets``; a folder of your frames: ``folders``)."""
