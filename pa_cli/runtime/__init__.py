"""Runtime plumbing: dask execution, numba's on-disk cache, the open3d preload."""
