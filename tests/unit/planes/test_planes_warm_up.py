"""The background warm-up of the plane kernels: it exercises every detection and association
kernel (its box room yields the six walls as planes), never raises into the caller, and plane
finding waits for it; on a first run the kernels compile in a process of their own."""

from __future__ import annotations

import os
import subprocess
import sys
import threading

import numpy as np
from numba.core.registry import CPUDispatcher

from pa_cli.config import PlanesConfig
from pa_cli.planes import kernels, warm_up
from pa_cli.planes.associate import build_plane_problem
from pa_cli.planes.warm_up import box_room_scan, warm_up_in_background

# the kernels a plane association calls from Python (the others are inlined into these)
ENTRY_KERNELS = ("scan_voxel_sums", "merge_voxel_sums", "fill_table",
                 "cell_neighbours", "label_points", "observation_moments")


def test_box_room_lies_on_six_walls():
    points = box_room_scan()
    on_wall = np.isclose(np.abs(points), warm_up.BOX_HALF_WIDTH_M).sum(axis=1)
    assert len(points) == 6 * warm_up.BOX_POINTS_PER_SIDE**2
    np.testing.assert_array_equal(on_wall, 1)  # every point on exactly one wall, none on an edge


def test_warm_up_finds_the_walls_and_loads_every_entry_kernel():
    assert warm_up.warm_up() == 6
    for name in ENTRY_KERNELS:
        kernel = getattr(kernels, name)
        assert isinstance(kernel, CPUDispatcher) and kernel.signatures, name


def test_warm_up_failure_is_not_raised(monkeypatch, caplog):
    def broken() -> int:
        raise RuntimeError("no kernels")

    monkeypatch.setattr(warm_up, "warm_up", broken)
    with caplog.at_level("DEBUG", logger="pa_cli.runtime.warm_up"):
        thread = warm_up_in_background()
        thread.join(timeout=60)
    assert not thread.is_alive() and thread.daemon
    assert "no kernels" in caplog.text


def test_plane_problem_does_not_wait_for_a_running_warm_up(monkeypatch):
    """The kernels are serial: plane finding runs beside a warm-up (numba's lock orders compilations)."""
    release = threading.Event()
    done = []

    def slow() -> int:
        release.wait(timeout=60)
        done.append(threading.current_thread().name)
        return 0

    monkeypatch.setattr(warm_up, "warm_up", slow)
    thread = warm_up_in_background()
    scan = box_room_scan()
    problem, _ = build_plane_problem([scan, scan.copy()], np.repeat(np.eye(4)[None], 2, axis=0), PlanesConfig())
    assert problem.n_planes == 6 and done == []  # built while the warm-up still ran
    release.set()
    thread.join(timeout=60)
    assert done == ["pa-plane-kernel-warm-up"]


def test_first_run_compiles_into_an_empty_cache_in_a_process_of_its_own(tmp_path):
    """`python -m pa_cli.planes.warm_up` (the compile process of `compile_in_background`) leaves every
    kernel it warms up in numba's cache: a process started after it finds them all cached."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    check = ("from pa_cli.planes.warm_up import WARM_UP_KERNELS;"
             "from pa_cli.runtime.numba_cache import is_cached;"
             "print(sum(map(is_cached, WARM_UP_KERNELS)), len(WARM_UP_KERNELS))")

    def cached() -> list[int]:
        out = subprocess.run([sys.executable, "-c", check], env=env, capture_output=True, text=True, check=True)
        return [int(v) for v in out.stdout.split()]

    n_cached, n_kernels = cached()
    assert n_cached == 0 and n_kernels == len(ENTRY_KERNELS) + 1  # an empty cache: none
    subprocess.run([sys.executable, "-m", "pa_cli.planes.warm_up"], env=env, check=True, capture_output=True)
    assert cached() == [n_kernels, n_kernels]


def test_compile_process_starts_only_when_a_kernel_is_missing(monkeypatch):
    started = []
    monkeypatch.setattr(warm_up, "start_compile_process", started.append)
    monkeypatch.setattr(warm_up, "is_cached", lambda kernel: True)
    warm_up.compile_in_background()
    assert started == []
    monkeypatch.setattr(warm_up, "is_cached", lambda kernel: kernel is not warm_up.WARM_UP_KERNELS[-1])
    warm_up.compile_in_background()
    assert started == ["pa_cli.planes.warm_up"]


def test_plane_finding_waits_for_a_running_compile_process(monkeypatch):
    """A kernel being compiled in the compile process is loaded from the cache after it, not compiled
    twice: plane finding starts only once the process has exited."""
    from pa_cli.runtime import warm_up as runtime_warm_up

    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(1.5)"])
    monkeypatch.setattr(runtime_warm_up, "_compiling", [process])
    scan = box_room_scan()
    build_plane_problem([scan, scan.copy()], np.repeat(np.eye(4)[None], 2, axis=0), PlanesConfig())
    assert process.poll() is not None  # it had exited when plane finding returned


def test_compile_process_compiles_this_runs_package_not_one_in_the_working_folder(tmp_path, monkeypatch):
    """Run from a folder holding another pa_cli (a checkout beside a `pip install .`), the compile
    process imports the package of this run: numba's cache is per source file."""
    from pa_cli.runtime import warm_up as runtime_warm_up

    marker = tmp_path / "imported-the-other-pa_cli"
    other = tmp_path / "pa_cli" / "planes"
    other.mkdir(parents=True)
    (tmp_path / "pa_cli" / "__init__.py").write_text("")
    (other / "__init__.py").write_text("")
    (other / "warm_up.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(runtime_warm_up, "_compiling", [])
    monkeypatch.setattr(runtime_warm_up, "_compiled_modules", set())
    runtime_warm_up.start_compile_process("pa_cli.planes.warm_up")
    assert len(runtime_warm_up._compiling) == 1
    assert runtime_warm_up._compiling[0].wait(timeout=600) == 0  # this package's warm-up ran and exited
    assert not marker.exists()
