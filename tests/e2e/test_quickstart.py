"""The README quickstart, run as a new user would: a fresh venv, `pip install .`, `pa refine`,
then `pip install -e ".[test]"` and `pa --version` (the editable install must still import).

It works on a copy of the repository in a temporary folder (the files git tracks, as a fresh clone
has them: outputs a user made in the checkout, such as the quickstart's own map, stay out), with
the per-user cache folder (`XDG_CACHE_HOME`, where numba's cache goes) also in that folder, so
nothing is left behind.
pip keeps using its own cache (`pip cache dir`), as it would for the user. Marked slow; the
default test run (and so CI) includes it.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]

COMMAND_TIMEOUT_S = 1200
COPY_IGNORE = shutil.ignore_patterns(".git", "__pycache__", "*.egg-info", "build", "dist", "out",
                                     ".pytest_cache", ".ruff_cache", ".venv*", "*.pyc")


def _copy_checkout(dest: Path) -> None:
    """The files git tracks, as they are in the working tree, into dest; without git (an unpacked
    source archive), the whole folder but build, cache and environment folders."""
    listed = subprocess.run(["git", "-C", str(REPO_ROOT), "ls-files", "-z"], capture_output=True)
    names = [n for n in listed.stdout.decode().split("\0") if n] if listed.returncode == 0 else []
    if not names:
        shutil.copytree(REPO_ROOT, dest, ignore=COPY_IGNORE)
        return
    for name in names:
        source = REPO_ROOT / name
        if source.is_file():  # a tracked file deleted in the working tree is left out
            (dest / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, dest / name)


def _quickstart_commands() -> list[list[str]]:
    """The `&&`-separated commands of the README's quickstart block, in order, as argv lists,
    without the test-suite run (this test is part of it)."""
    readme = (REPO_ROOT / "README.md").read_text()
    section = readme[readme.index("## Quickstart"):]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    commands = []
    for line in block.strip().splitlines():
        for part in line.split("&&"):
            argv = shlex.split(part)
            if argv[:3] != ["python", "-m", "pytest"]:
                commands.append(argv)
    return commands


def _run(argv: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    exe = shutil.which(argv[0], path=env["PATH"])
    assert exe is not None, f"{argv[0]} not found on {env['PATH']}"
    result = subprocess.run([exe, *argv[1:]], cwd=cwd, env=env, capture_output=True, text=True,
                            timeout=COMMAND_TIMEOUT_S, stdin=subprocess.DEVNULL)
    assert result.returncode == 0, (f"`{shlex.join(argv)}` exited {result.returncode}\n"
                                    f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result


def _numba_cache_files(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.suffix in (".nbi", ".nbc")]


@pytest.mark.slow
def test_readme_quickstart_in_a_fresh_venv_keeps_the_install_working(tmp_path):
    commands = _quickstart_commands()
    assert commands[0] == ["pip", "install", "."] and commands[1][:2] == ["pa", "refine"], commands
    assert ["pip", "install", "-e", ".[test]"] in commands[2:], commands

    repo = tmp_path / "repo"
    _copy_checkout(repo)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=COMMAND_TIMEOUT_S)
    pip_cache = subprocess.run([sys.executable, "-m", "pip", "cache", "dir"], capture_output=True,
                               text=True).stdout.strip()
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "PYTHONPATH", "VIRTUAL_ENV")}
    bin_dir = venv / ("Scripts" if os.name == "nt" else "bin")
    env.update(PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(venv),
               XDG_CACHE_HOME=str(tmp_path / "cache"), PIP_DISABLE_PIP_VERSION_CHECK="1")
    if pip_cache and Path(pip_cache).is_dir():
        env["PIP_CACHE_DIR"] = pip_cache

    _run(commands[0], repo, env)  # pip install .
    _run(commands[1], repo, env)  # pa refine ... (compiles and caches the numba kernels)
    site_packages = Path(subprocess.run(
        [str(bin_dir / "python"), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, env=env, check=True).stdout.strip())
    assert (site_packages / "pa_cli").is_dir()
    assert _numba_cache_files(site_packages / "pa_cli") == []
    assert _numba_cache_files(repo) == []
    if sys.platform.startswith("linux"):  # platformdirs follows XDG_CACHE_HOME on Linux only
        assert _numba_cache_files(tmp_path / "cache" / "pa_cli" / "numba")

    for argv in commands[2:]:
        _run(argv, repo, env)  # pip install -e ".[test]"
    assert not (site_packages / "pa_cli").exists()  # nothing left to shadow the editable install
    version = _run(["pa", "--version"], tmp_path, env)
    assert version.stdout.strip() == f"pa {_project_version()}"


def _project_version() -> str:
    return re.search(r'^version = "(.+)"', (REPO_ROOT / "pyproject.toml").read_text(), re.M).group(1)
