"""Where a `pa` command reaches its peak memory: the resident memory sampled while it runs, with the code
running at each new high (prints a table).

    PYTHONPATH=. python bench/memory_peaks.py refine SCANS --out DIR/map.ply --config outdoor --loops -q

The command runs in this process (its arguments as `pa` takes them). A thread reads the process's
resident memory (/proc/self/statm, Linux) every SAMPLE_S seconds; each time it exceeds the highest so
far by STEP_GB it records the time, the memory and the innermost STACK_DEPTH frames of `pa_cli` code
the main thread is running. The table lists those highs; its title gives the process's peak resident
memory as the kernel counted it (ru_maxrss), which a sample may miss by a few tens of MB.
"""

from __future__ import annotations

import os
import resource
import sys
import threading
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.common import markdown_table  # noqa: E402

SAMPLE_S = 0.05  # a numpy temporary of a few hundred MB lives for tens of milliseconds or more
STEP_GB = 0.05  # a new high is recorded when it exceeds the last by this much
STACK_DEPTH = 4  # pa_cli frames shown per high, innermost last


def resident_gb() -> float:
    """The process's resident memory now (GB)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e9


def watch(main_thread: int, highs: list[tuple[float, float, str]], stop: threading.Event) -> None:
    """Append (seconds since the start, GB, pa_cli frames of the main thread) at every new high until `stop`."""
    start, high = time.perf_counter(), 0.0
    while not stop.is_set():
        now_gb = resident_gb()
        if now_gb > high + STEP_GB:
            high = now_gb
            frame = sys._current_frames().get(main_thread)
            frames = [f"{Path(f.filename).stem}:{f.lineno} {f.name}" for f in traceback.extract_stack(frame)
                      if "pa_cli" in f.filename]
            highs.append((time.perf_counter() - start, now_gb, " > ".join(frames[-STACK_DEPTH:])))
        stop.wait(SAMPLE_S)


def main() -> None:
    from pa_cli.cli.main import run

    highs: list[tuple[float, float, str]] = []
    stop = threading.Event()
    watcher = threading.Thread(target=watch, args=(threading.get_ident(), highs, stop), daemon=True)
    watcher.start()
    code = run(sys.argv[1:])
    stop.set()
    watcher.join()
    # one row per place: the highest value reached there, in order of time
    rows: dict[str, list] = {}
    for seconds, gb, where in highs:
        rows[where] = [f"{seconds:.1f}", f"{gb:.2f}", where]
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9  # Linux: kB
    markdown_table(f"New highs of resident memory, `pa {' '.join(sys.argv[1:])}` (exit code {code}; peak "
                   f"{peak_gb:.2f} GB)",
                   ["s", "GB", "pa_cli code running (innermost last)"], list(rows.values()))


if __name__ == "__main__":
    main()
