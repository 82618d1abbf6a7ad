"""Refinement: a flow network's prediction fused with the road model inside the road mask."""
