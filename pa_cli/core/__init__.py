"""Shared maths: rigid-body geometry, point clusters, voxel keys, the feature problem, the local frame."""
