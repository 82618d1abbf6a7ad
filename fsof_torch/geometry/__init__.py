"""Geometry: the camera (intrinsics and mounting over the road), the road's motion models and
their flow, and ego-motion from poses and vehicle signals."""
