"""The `pa` command line: `app` (typer), one module per command, `main.run` mapping errors to exit codes."""

from pa_cli.cli.main import app, main, run

__all__ = ["app", "main", "run"]
