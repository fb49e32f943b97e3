"""pa: LiDAR map refinement by second-order plane adjustment."""

__version__ = "0.1.0"
