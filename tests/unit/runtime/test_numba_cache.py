"""numba's cache goes to the per-user cache folder (or NUMBA_CACHE_DIR), never into the package."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

PROBE = ("import {first}; import pa_cli.adjust.linalg, pa_cli.planes.kernels, os; "
         "from numba.core import config; print(os.environ['NUMBA_CACHE_DIR']); print(config.CACHE_DIR)")


def _cache_dirs(tmp_path: Path, first: str, numba_cache_dir: str | None) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    if numba_cache_dir is not None:
        env["NUMBA_CACHE_DIR"] = numba_cache_dir
    out = subprocess.run([sys.executable, "-c", PROBE.format(first=first)], env=env, capture_output=True,
                         text=True, check=True, cwd=tmp_path).stdout
    return out.split()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="platformdirs follows XDG_CACHE_HOME on Linux")
@pytest.mark.parametrize("first", ["numpy", "numba"])  # numba imported before pa_cli, or not
def test_cache_goes_to_the_user_cache_folder(tmp_path, first):
    expected = str(tmp_path / "xdg" / "pa_cli" / "numba")
    assert _cache_dirs(tmp_path, first, None) == [expected, expected]
    assert (tmp_path / "xdg" / "pa_cli" / "numba").is_dir()


def test_a_user_setting_is_kept(tmp_path):
    chosen = str(tmp_path / "mine")
    assert _cache_dirs(tmp_path, "numba", chosen) == [chosen, chosen]


ANNOUNCE = """
import logging, sys
logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s")
import numpy as np
from pa_cli.core import neighbourhoods
from pa_cli.runtime.numba_cache import announce_compilation, is_cached
kernel = neighbourhoods._neighbourhood_moments
print("cached before:", is_cached(kernel))
points = np.random.default_rng(0).normal(size=(50, 3))
neighbourhoods.neighbourhood_fit(points, points[:5], 1.0, 3, 1e-3)  # announces, then compiles and caches
neighbourhoods.neighbourhood_fit(points, points[:5], 1.0, 3, 1e-3)
print("cached after:", is_cached(kernel))
print("announced again:", announce_compilation([kernel]))
"""


def test_the_first_compilation_is_announced_once(tmp_path):
    """A run with an empty cache says once that it compiles; the run after it (cache filled) says nothing."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    first, second = (subprocess.run([sys.executable, "-c", ANNOUNCE], env=env, capture_output=True, text=True,
                                    check=True, cwd=tmp_path).stdout for _ in range(2))
    assert first.count("compiling numerical kernels once") == 1 and str(tmp_path / "cache") in first
    assert "cached before: False" in first and "cached after: True" in first
    assert "compiling" not in second and "cached before: True" in second
    assert "announced again: False" in first + second
