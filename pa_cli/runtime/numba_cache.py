"""Where numba keeps its on-disk cache of compiled kernels: never inside the installed package.

The kernels are compiled with `cache=True`. Without `NUMBA_CACHE_DIR`, numba writes its cache
next to the source (`site-packages/pa_cli/*/__pycache__`); pip does not remove those folders on
uninstall, and the left-over `pa_cli/` folder then shadows a later editable install of the
package. Every module with numba kernels imports this module before it defines them: it points
`NUMBA_CACHE_DIR` at the per-user cache folder `<user cache dir>/pa_cli/numba` (platformdirs:
`$XDG_CACHE_HOME` or `~/.cache` on Linux, `~/Library/Caches` on macOS, `%LOCALAPPDATA%` on
Windows) unless the user has set it, and tells numba's config when numba is already imported
(numba picks the cache folder when a kernel is decorated, not when numba is imported). When that
folder cannot be created, a folder in the system's temporary directory is used instead, so that
numba never falls back to the package.

`announce_compilation(kernels)` says once per process, in one log line, that numba is compiling
when some of the kernels about to run have no usable entry in the cache (the first run, or the
first after an upgrade): their index files are missing or stale, read without compiling anything.
"""

from __future__ import annotations

import logging
import os
import pickle
import sys
import tempfile
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)

CACHE_DIR_VARIABLE = "NUMBA_CACHE_DIR"


def default_cache_dir() -> Path:
    """The per-user folder for pa's numba cache (`<user cache dir>/pa_cli/numba`)."""
    from platformdirs import user_cache_dir

    return Path(user_cache_dir("pa_cli", appauthor=False)) / "numba"


def _writable_cache_dir() -> Path:
    user = f"-{os.getuid()}" if hasattr(os, "getuid") else ""
    fallback = Path(tempfile.gettempdir()) / f"pa_cli-numba{user}"
    for candidate in (default_cache_dir(), fallback):
        try:
            candidate.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(candidate, os.W_OK):
            return candidate
    return fallback


def configure_cache_dir() -> str:
    """Set `NUMBA_CACHE_DIR` (unless set by the user) and return the folder numba will use."""
    if not os.environ.get(CACHE_DIR_VARIABLE):
        os.environ[CACHE_DIR_VARIABLE] = str(_writable_cache_dir())
    cache_dir = os.environ[CACHE_DIR_VARIABLE]
    if "numba" in sys.modules:  # numba read its config already: tell it too
        from numba.core import config

        if not config.CACHE_DIR:
            config.CACHE_DIR = cache_dir
    return cache_dir


_announced: list[bool] = []  # the compilation was said (at most once per process)


def is_cached(kernel: object) -> bool:
    """Whether numba's on-disk cache holds a compiled version of a kernel (a dispatcher with
    `cache=True`) for its current source: its index file exists, is of this numba and matches the
    source (numba's own check, `IndexDataCacheFile._load_index`, which reads the small index only).
    True when that cannot be told (a kernel without a cache, numba's internals changed)."""
    try:
        return bool(kernel._cache._cache_file._load_index())  # type: ignore[attr-defined]
    except (AttributeError, OSError, EOFError, pickle.UnpicklingError, ValueError):
        return True


def announce_compilation(kernels: Iterable[object]) -> bool:
    """Log one line, once per process, when some of `kernels` are not in numba's cache (they are
    about to be compiled, which takes seconds; later runs load them). Returns whether it logged."""
    if _announced:
        return False
    cold = [kernel for kernel in kernels if not is_cached(kernel)]
    if not cold:
        return False
    _announced.append(True)
    log.info("compiling numerical kernels once (cached in %s; later runs load them) ...", configure_cache_dir())
    return True


configure_cache_dir()
