"""Geometry: pinhole cameras and their rays, normalized device coordinates, boxes, camera paths."""
