"""Kernels loaded ahead of their first use on a thread of their own, and the wait for it.

The kernels are serial (no prange): a thread may run them while a warm-up compiles or loads
others; numba's compiler lock orders the compilations, and a kernel the warm-up is compiling is
compiled once (the caller waits for it). `wait_for_warm_up` joins a running warm-up (one at a time).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from pa_cli.errors import PaError

log = logging.getLogger(__name__)

_running: list[threading.Thread] = []  # the warm-up threads started (at most one is alive)


def start_warm_up(load: Callable[[], object], name: str) -> threading.Thread:
    """Start `load` on a daemon thread (after any running warm-up) and return it; a failure is
    logged (debug), never raised: the kernels then load at their first real use."""
    def run() -> None:
        try:
            load()
        except (PaError, ImportError, ValueError, RuntimeError, OSError) as error:
            log.debug("kernel warm-up %s failed (%s); the kernels load at first use.", name, error)

    wait_for_warm_up()
    thread = threading.Thread(target=run, name=name, daemon=True)
    _running[:] = [thread]
    thread.start()
    return thread


def wait_for_warm_up() -> None:
    """Return when no warm-up runs (at once on the warm-up's own thread)."""
    for thread in _running:
        if thread is not threading.current_thread():
            thread.join()
