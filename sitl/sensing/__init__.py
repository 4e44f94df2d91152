"""Sensing the world without the payload in the loop: the vectorised 1D LiDAR sample path, and the
2D/3D comparison scanners."""
