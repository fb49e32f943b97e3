"""Kernels loaded ahead of their first use on a thread of their own, compiled ahead in a process of
their own on a first run, and the wait for both.

The kernels are serial (no prange): a thread may run them while a warm-up compiles or loads
others; numba's compiler lock orders the compilations, and a kernel the warm-up is compiling is
compiled once (the caller waits for it). A new warm-up first joins a running one (one at a time);
`wait_for_compile_processes` waits for a running compile process.

Compiling is Python work that holds the interpreter lock: on a thread it shares one interpreter
with the reading of the scans and the odometry. `start_compile_process` runs a module that compiles
kernels into numba's on-disk cache in a separate process, in parallel with the whole start of the
run; the run then loads them from the cache (`pa_cli.runtime.numba_cache`).
"""

from __future__ import annotations

import atexit
import logging
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import pa_cli
from pa_cli.errors import PaError

log = logging.getLogger(__name__)

_running: list[threading.Thread] = []  # the warm-up threads started (at most one is alive)
_compiling: list[subprocess.Popen] = []  # the compile processes started (at most one per module)
_compiled_modules: set[str] = set()
# `python -m` looks in its working folder first: there, the folder holding this run's pa_cli, so that the
# process compiles the same files (numba's cache is per source file), not a checkout in the user's folder
PACKAGE_PARENT = Path(pa_cli.__file__).resolve().parents[1]


def start_warm_up(load: Callable[[], object], name: str) -> threading.Thread:
    """Start `load` on a daemon thread (after any running warm-up) and return it; a failure is
    logged (debug), never raised: the kernels then load at their first real use."""
    def run() -> None:
        try:
            load()
        except (PaError, ImportError, ValueError, RuntimeError, OSError) as error:
            log.debug("kernel warm-up %s failed (%s); the kernels load at first use.", name, error)

    _join_warm_up_threads()  # one warm-up at a time; a compile process goes on beside the new one
    thread = threading.Thread(target=run, name=name, daemon=True)
    _running[:] = [thread]
    thread.start()
    return thread


def start_compile_process(module: str) -> None:
    """Run `python -m module` (which compiles kernels into numba's cache and exits) in a process of
    its own, once per module and process, quiet (its output discarded; a failure only means the
    kernels compile at their first use); it is stopped when this process exits before it."""
    if module in _compiled_modules:
        return
    _compiled_modules.add(module)
    try:
        process = subprocess.Popen([sys.executable, "-m", module], cwd=PACKAGE_PARENT, stdin=subprocess.DEVNULL,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError as error:
        log.debug("could not start the compile process %s (%s); the kernels compile at first use.", module, error)
        return
    _compiling.append(process)
    atexit.register(process.kill)  # no-op once it has exited


def wait_for_compile_processes() -> None:
    """Return when no compile process runs."""
    for process in _compiling:
        process.wait()


def _join_warm_up_threads() -> None:
    for thread in _running:
        if thread is not threading.current_thread():
            thread.join()
