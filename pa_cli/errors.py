"""The exception hierarchy of `pa`.

Library code raises these; only `pa_cli.cli` turns them into messages and exit codes
(1 for a `PaError`, 2 for a `UsageError`). Messages name the file, what was expected,
what was found and, where one exists, the flag that fixes it.
"""

from __future__ import annotations


class PaError(Exception):
    """A known, user-facing failure (exit code 1)."""

    exit_code = 1


class InputError(PaError):
    """An input file or folder is missing, unreadable or holds bad values."""


class FormatError(InputError):
    """A file exists but does not have the expected format (columns, header, shapes)."""


class ConfigError(PaError):
    """A configuration file or value is invalid."""


class OutputError(PaError):
    """An output cannot be written (exists without --force, would overwrite an input, ...)."""


class SolverError(PaError):
    """The solver cannot run on the given problem (for example: nothing to optimise)."""


class UsageError(PaError):
    """Arguments that contradict each other or are out of range (exit code 2)."""

    exit_code = 2


class QualityError(PaError):
    """`pa refine --strict`: the quality verdict is not 'improved' (the outputs were written)."""
