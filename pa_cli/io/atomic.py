"""Atomic, overwrite-safe output writing.

Every output of `pa` goes through `atomic_path`: the data is written to a temporary file in
the destination folder and renamed into place only when the write succeeded, so a failure
never leaves a half-written file. Existing files are refused unless `force` is set.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from pa_cli.errors import OutputError

_UMASK = os.umask(0)
os.umask(_UMASK)


def check_writable(paths: Iterable[Path], force: bool, inputs: Iterable[Path] = ()) -> None:
    """Refuse outputs that exist (unless `force`) or that would overwrite an input.

    Call this for all outputs of a command before doing any work, so nothing is
    half-done when an output is refused.
    """
    input_set = {Path(p).resolve() for p in inputs}
    for path in paths:
        path = Path(path)
        if path.resolve() in input_set:
            raise OutputError(f"{path}: refusing to overwrite an input file; choose another output path.")
        if path.exists() and not force:
            raise OutputError(f"{path} already exists; pass --force to overwrite it.")
        if path.exists() and path.is_dir():
            raise OutputError(f"{path} is a directory; expected a file path.")
        parent = path.parent if str(path.parent) else Path(".")
        if not parent.exists():
            raise OutputError(f"{path}: the folder {parent} does not exist; create it first.")


def apply_umask(path: Path) -> None:
    """Give a `mkstemp` file (0600) or `mkdtemp` folder (0700) the mode the umask gives new ones."""
    os.chmod(path, (0o777 if Path(path).is_dir() else 0o666) & ~_UMASK)


@contextlib.contextmanager
def atomic_path(path: Path | str, force: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to `path`; rename it onto `path` if the block succeeds."""
    path = Path(path)
    check_writable([path], force)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix,
                                    dir=path.parent if str(path.parent) else ".")
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        apply_umask(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text_atomic(path: Path | str, text: str, force: bool = False) -> None:
    """Write `text` to `path` atomically."""
    with atomic_path(path, force) as tmp:
        tmp.write_text(text)
