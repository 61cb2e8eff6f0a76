"""Batched per-frame geometry: height, contact, normals, curvature, the Frame type."""
