"""Estimation: the robust solver, road-motion fits to flow and to images, V-flow analysis and
freespace detection."""
