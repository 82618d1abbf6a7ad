"""Training: unsupervised and freespace loss terms, and a small RAFT-style test network."""
