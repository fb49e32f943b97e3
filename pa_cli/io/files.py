"""Opening input files: one set of checks and messages for every reader.

A missing path, a folder where a file is expected and an unreadable file are `InputError`s
naming the path, the kind of file expected and, where given, where to find a valid one.
"""

from __future__ import annotations

from pathlib import Path

from pa_cli.errors import InputError


def check_input_file(path: Path, what: str, hint: str = "") -> None:
    """Raise `InputError` unless `path` is an existing file; `what` names the expected file kind."""
    suffix = f" ({hint})" if hint else ""
    if not path.exists():
        raise InputError(f"{path}: {what} file not found{suffix}.")
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a {what} file{suffix}.")


def read_input_bytes(path: Path, what: str, hint: str = "") -> bytes:
    """The bytes of the input file `path`, after `check_input_file`; read errors are `InputError`s."""
    check_input_file(path, what, hint)
    try:
        return path.read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the {what} file ({exc.strerror or exc}).") from None
