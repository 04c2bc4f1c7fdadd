"""Geometry both rooms stand on: frames and poses, the camera, the rasteriser, silhouette borders."""
