"""Shared fixtures. Real data lives in ../shared/data (never copied into the repo)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _find_shared_data() -> Path:
    """../shared/data beside the repository (or beside a parent folder, for git worktrees)."""
    if os.environ.get("PA_SHARED_DATA"):
        return Path(os.environ["PA_SHARED_DATA"])
    for parent in REPO_ROOT.parents:
        candidate = parent / "shared" / "data"
        if candidate.is_dir():
            return candidate
    return REPO_ROOT.parent / "shared" / "data"


SHARED_DATA = _find_shared_data()


@pytest.fixture
def shared_data() -> Path:
    """../shared/data; tests using it skip cleanly when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"{SHARED_DATA} not present")
    return SHARED_DATA


@pytest.fixture
def run_pa(capsys):
    """Run the CLI in-process: returns (exit_code, stdout, stderr)."""
    from pa_cli.cli import run

    def _run(*args: str):
        code = run([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return _run


@pytest.fixture(autouse=True)
def pa_logger_restored():
    """The `pa_cli` logger as each test found it: a command run in-process (`run_pa`) gives it its own
    handler and stops propagation (`pa_cli.cli.app.setup_logging`), which would hide later tests'
    records from pytest's `caplog`."""
    import logging

    logger = logging.getLogger("pa_cli")
    state = (list(logger.handlers), logger.level, logger.propagate)
    yield
    logger.handlers[:], logger.level, logger.propagate = state
