"""Fused voxel uncertainty grid and the next-best-view service."""
