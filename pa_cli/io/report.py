"""Reports: JSON serialisation and atomic writing.

Every JSON report `pa` writes (refine, adjust, eval) starts with `report_version`, raised
whenever a key is renamed or removed, so scripts reading reports can check what they get:
`REPORT_VERSION` here for the refine and eval reports; the solver report (`pa adjust
--report`, and each round of the refine report) carries its own, `pa_cli.adjust.REPORT_VERSION`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli.io.atomic import atomic_path

REPORT_VERSION = 4


def json_value(value: Any) -> Any:
    """A value `json.dumps` cannot write, as one it can (its `default`): numpy arrays as lists, numpy
    scalars as Python numbers, anything else (paths) as its text."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


def report_to_json(report: dict[str, Any]) -> str:
    """The report as indented JSON with `report_version` first; numpy values and paths converted.

    A report that holds its own `report_version` (the solver report) keeps its value.
    """
    versioned = {"report_version": REPORT_VERSION, **report}
    return json.dumps(versioned, indent=2, default=json_value) + "\n"


def write_report(path: Path | str, report: dict[str, Any], force: bool = False) -> None:
    """Write `report_to_json(report)` to `path`, atomically."""
    with atomic_path(path, force) as tmp:
        tmp.write_text(report_to_json(report))
