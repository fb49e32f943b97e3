"""Helpers shared by the benchmark scripts: the repository and shared-data paths, running `pa` in a
subprocess and printing result tables. Run the scripts from the repository root with PYTHONPATH=."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("PA_SHARED_DATA") or next(
    (p / "shared" / "data" for p in REPO.parents if (p / "shared" / "data").is_dir()), REPO.parent / "shared" / "data"))


def run_pa(*args: object, check: bool = True) -> subprocess.CompletedProcess:
    """Run `python -m pa_cli ARGS` from this checkout; with `check`, exit with its stderr on failure."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-m", "pa_cli", *map(str, args)], env=env,
                          capture_output=True, text=True)
    if check and proc.returncode != 0:
        raise SystemExit(f"pa {' '.join(map(str, args))} failed:\n{proc.stderr}")
    return proc


# Runs its arguments as a command and prints, as the last line of stdout, its peak memory (kB), wall time (s) and CPU
# time (s). Peak memory: the larger of the process tree's resident memory summed (the command and the processes it
# starts: a local dask cluster, the pair registrations' pool), sampled every PEAK_SAMPLE_S, and the largest single
# process's ru_maxrss (between samples). Wall: from the command's start (the interpreter's start-up and imports
# included) to its end. CPU: user and system time of the command and of every process it waited for.
PEAK_SAMPLE_S = 0.05
_MEASURED = f"""
import resource, subprocess, sys, time
import psutil
start = time.perf_counter()
child = subprocess.Popen(sys.argv[1:])
peak = 0
while child.poll() is None:
    try:
        tree = [psutil.Process(child.pid), *psutil.Process(child.pid).children(recursive=True)]
        peak = max(peak, sum(p.memory_info().rss for p in tree))
    except psutil.Error:  # a process of the tree ended while it was summed: the next sample counts
        pass
    time.sleep({PEAK_SAMPLE_S})
wall = time.perf_counter() - start
usage = resource.getrusage(resource.RUSAGE_CHILDREN)
print(max(peak // 1024, usage.ru_maxrss), wall, usage.ru_utime + usage.ru_stime)
sys.exit(child.returncode)
"""


@dataclass(frozen=True)
class Measured:
    """A `pa` run's peak memory (GB, the process tree's), wall time (s, its start-up included) and CPU time (s, its
    processes')."""

    peak_gb: float
    wall_s: float
    cpu_s: float


def run_pa_measured(*args: object) -> Measured:
    """Run `python -m pa_cli ARGS` from this checkout in a child of its own (`_MEASURED`); exits with its stderr on
    failure."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", _MEASURED, sys.executable, "-m", "pa_cli", *map(str, args)],
                          env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"pa {' '.join(map(str, args))} failed:\n{proc.stderr}")
    peak_kb, wall_s, cpu_s = proc.stdout.strip().splitlines()[-1].split()
    return Measured(int(peak_kb) * 1024 / 1e9, float(wall_s), float(cpu_s))


def shared_sequences(names: tuple[str, ...]) -> Iterator[tuple[str, Path]]:
    """(name, folder) of each named sequence under SHARED; says which ones are missing and skips them."""
    for name in names:
        folder = SHARED / name
        if folder.is_dir():
            yield name, folder
        else:
            print(f"skip {name}: {folder} not present")


def print_table(title: str, header: list[str], rows: list[list]) -> None:
    """A Markdown table with padded columns, under `title`."""
    print(f"\n{title}")
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows, strict=True)]
    print("| " + " | ".join(str(h).ljust(w) for h, w in zip(header, widths, strict=True)) + " |")
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for row in rows:
        print("| " + " | ".join(str(x).ljust(w) for x, w in zip(row, widths, strict=True)) + " |")


def markdown_table(title: str, cols: list[str], rows: list[list]) -> None:
    """A Markdown table under a `###` heading, floats to 3 significant digits, flushed at once."""
    print(f"\n### {title}\n")
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for r in rows:
        print("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in r) + " |")
    sys.stdout.flush()
