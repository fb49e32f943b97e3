"""The stages' progress bars and their wall time, CPU time and peak memory."""

from __future__ import annotations

import contextlib
import os
import resource
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from typing import Protocol

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.progress import Progress as ProgressBar

from pa_cli.runtime.distributed import GB
from pa_cli.runtime.heap import release_free_heap

Progress = Callable[[int, int], None]  # (done, total) of the running stage


class Stage(Protocol):
    """Opens a labelled stage: `with stage("planes 1", total=n) as progress: progress(k, n)`."""

    def __call__(self, name: str, total: int | None = None) -> AbstractContextManager[Progress]: ...


def cpu_s() -> float:
    """CPU time (s, user and system) of this process, all threads, and of its child processes that ended (the
    processes a stage starts and joins: the pair registrations')."""
    times = os.times()
    return times.user + times.system + times.children_user + times.children_system


def peak_rss_gb() -> float:
    """This process's peak resident set size so far (GB; Linux reports ru_maxrss in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / GB


class StageClock:
    """A `Stage`: a progress bar on stderr per stage (none when `show_progress` is false) with the
    time elapsed and the time remaining (estimated from the rate so far; blank while unknown); the
    wall time (s) and the CPU time (s, `cpu_s`: all threads, and the processes the stage joined) of
    each stage name add up over its runs, and the process's peak RSS (GB) at each stage's end is
    kept; `elapsed_s` is the wall time since the clock was made, the work between the stages included. At
    each stage's end the C heap's free pages go back to the operating system
    (`release_free_heap`), so what one stage freed does not stay resident under the next."""

    def __init__(self, show_progress: bool) -> None:
        self.show_progress = show_progress
        self.started = time.perf_counter()
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}
        self.peak_rss_gb: dict[str, float] = {}

    def elapsed_s(self) -> float:
        """Wall time (s) since the clock was made: the stages and the work between them."""
        return time.perf_counter() - self.started

    @contextlib.contextmanager
    def __call__(self, name: str, total: int | None = None) -> Iterator[Progress]:
        start, start_cpu = time.perf_counter(), cpu_s()
        with ProgressBar(TextColumn("[bold]{task.description:<18}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), console=Console(stderr=True),
                      disable=not self.show_progress, transient=False) as bar:
            task = bar.add_task(name, total=total)

            def update(done: int, total_now: int) -> None:
                bar.update(task, completed=done, total=total_now)

            yield update
        self.wall_s[name] = self.wall_s.get(name, 0.0) + time.perf_counter() - start
        self.cpu_s[name] = self.cpu_s.get(name, 0.0) + cpu_s() - start_cpu
        self.peak_rss_gb[name] = peak_rss_gb()
        release_free_heap()
