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
