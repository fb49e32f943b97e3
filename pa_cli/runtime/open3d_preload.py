"""Import Open3D on machines without a system libusb.

Open3D's Python module links `libusb-1.0.so.0`. Fresh machines often lack it and we may not
use apt, so the PyPI package `libusb-package` ships the library and we preload it with
RTLD_GLOBAL before the first `import open3d`. Import Open3D only through `open3d()`.
"""

from __future__ import annotations

import ctypes
import functools
from types import ModuleType


@functools.cache
def open3d() -> ModuleType:
    """Return the `open3d` module, preloading the bundled libusb first if needed."""
    try:
        import libusb_package

        library_path = libusb_package.get_library_path()
        if library_path is not None:
            ctypes.CDLL(str(library_path), mode=ctypes.RTLD_GLOBAL)
    except (ImportError, OSError):  # a system libusb may still be there
        pass
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d
