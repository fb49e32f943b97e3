"""The work folder of `pa refine`: each finished stage's result, so a stopped run continues.

`MAP.work/` (next to the outputs, named after the map's stem) holds one `.npz` per finished
stage, each written to a temporary file and renamed into place:

    manifest.json       the inputs' identity (scans, --poses, --topic, --glob, config, pa version)
    odometry.npz        the initial poses (KISS-ICP or --poses) and the local frame's origin
    loops.npz           the loop-closed poses and the loops' record
    motions.npz         the registered relative motions of the odometry factors
    round.npz           what the next round starts from (`pa_cli.refine.state.RoundsCarry`)

`pa refine ... --resume` loads what is there and runs only the rest; a work folder made for
other inputs or another config is refused. The run removes the folder when its outputs are
written (unless `--keep-work`).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from pathlib import Path
from typing import Any

import numpy as np

from pa_cli import __version__
from pa_cli.config import PaConfig
from pa_cli.errors import InputError, OutputError
from pa_cli.io.atomic import apply_umask, write_text_atomic
from pa_cli.io.report import json_value
from pa_cli.planes.edges import EdgeLabels
from pa_cli.planes.labels import PointLabels
from pa_cli.refine.state import RoundsCarry
from pa_cli.sources import ScanSubset

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
# execution keys that bound memory and never change a result: a resumed run may change them
# (the memory warnings name execution.memory_budget_gb)
RESULT_NEUTRAL_KEYS = ("memory_budget_gb", "cache_budget_gb")


def work_folder_path(map_path: Path | str) -> Path:
    """The work folder of the map `map_path`: `MAP.work` beside it."""
    map_path = Path(map_path)
    return map_path.with_name(map_path.stem + ".work")


def files_identity(path: Path) -> dict[str, Any]:
    """The identity of a file or of every file below a folder: how many, their bytes in all and
    a digest of their relative paths, sizes and modification times (reads no contents)."""
    path = Path(path)
    if path.is_file():
        entries = [(path.name, path.stat())]
    else:
        entries = sorted((str(p.relative_to(path)), p.stat()) for p in path.rglob("*") if p.is_file())
    digest = hashlib.sha256()
    for name, stat in entries:
        digest.update(f"{name}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return {"path": str(path.resolve()), "n_files": len(entries),
            "n_bytes": int(sum(stat.st_size for _, stat in entries)), "digest": digest.hexdigest()}


def config_digest(config: PaConfig) -> str:
    """A digest of every config key that can change a result (all but `RESULT_NEUTRAL_KEYS`)."""
    values = config.model_dump(mode="json")
    for key in RESULT_NEUTRAL_KEYS:
        values["execution"].pop(key, None)
    return hashlib.sha256(json.dumps(values, sort_keys=True).encode()).hexdigest()


def manifest(scans: Path, n_scans: int, topic: str | None, glob: str | None, subset: ScanSubset | None,
             poses: Path | None, config: PaConfig) -> dict[str, Any]:
    """What a work folder was made for: the scans (and their count), --topic, --glob,
    --first/--last/--every, --poses, the config and the pa version."""
    return {"pa_version": __version__, "scans": files_identity(scans), "n_scans": int(n_scans), "topic": topic,
            "glob": glob, "subset": None if subset is None else subset.describe(),
            "poses": None if poses is None else files_identity(poses),
            "config_digest": config_digest(config)}


def _differences(found: dict[str, Any], expected: dict[str, Any]) -> list[str]:
    """The manifest entries that differ, in words."""
    words = {"pa_version": "the pa version", "scans": "the scans (files, sizes or times)", "n_scans": "the scan count",
             "topic": "--topic", "glob": "--glob",
             "subset": "--first/--last/--every", "poses": "--poses", "config_digest": "the config"}
    return [words.get(key, key) for key in expected if found.get(key) != expected[key]]


class WorkFolder:
    """The stages' results of one run in `path` (`open_work_folder` makes or checks it)."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._pending: Future | None = None  # a carry being written (`save_carry`)

    def save(self, name: str, arrays: dict[str, Any], record: dict[str, Any] | None = None) -> None:
        """Write `name`.npz atomically: the arrays, and `record` (JSON-ready values) as text."""
        self._write(name, arrays, None if record is None else json.dumps(record, default=json_value))

    def _write(self, name: str, arrays: dict[str, Any], record_json: str | None) -> None:
        """Write `name`.npz atomically: the arrays, and the record's JSON text when there is one."""
        payload = dict(arrays)
        if record_json is not None:
            payload["record_json"] = np.array(record_json)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{name}.", suffix=".tmp.npz", dir=self.path)
        os.close(fd)
        try:
            np.savez(tmp_name, **payload)
            apply_umask(Path(tmp_name))
            os.replace(tmp_name, self.path / f"{name}.npz")
        finally:
            if os.path.exists(tmp_name):
                os.unlink(tmp_name)

    def load(self, name: str) -> tuple[dict[str, np.ndarray], dict[str, Any] | None] | None:
        """The arrays and the record of `name`.npz, or None when that stage has not finished."""
        self.wait()
        path = self.path / f"{name}.npz"
        if not path.exists():
            return None
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files if key != "record_json"}
            record = json.loads(str(data["record_json"])) if "record_json" in data.files else None
        return arrays, record

    def load_motions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any] | None] | None:
        """The registered relative motions (R_z (N-1, 3, 3), t_z (N-1, 3) m), their sigmas (N-1, 6; rad, m) and
        the record of their measured noise (None: not measured), or None."""
        kept = self.load("motions")
        if kept is None:
            return None
        arrays, record = kept
        return arrays["R_z"], arrays["t_z"], arrays["sigmas"], record

    def save_motions(self, R_z: np.ndarray, t_z: np.ndarray, sigmas: np.ndarray,
                     noise: dict[str, Any] | None) -> None:
        """Keep the registered relative motions of the odometry factors, their sigmas and the record of their
        measured noise."""
        self.save("motions", {"R_z": R_z, "t_z": t_z, "sigmas": sigmas}, noise)

    def load_carry(self) -> RoundsCarry | None:
        """What the next round starts from (`RoundsCarry`), or None when no round finished."""
        kept = self.load("round")
        if kept is None:
            return None
        arrays, record = kept
        assert record is not None  # `save_carry` writes one
        fixed_point = {key.removeprefix("fixed_point_"): value for key, value in arrays.items()
                       if key.startswith("fixed_point_")}
        return RoundsCarry(int(arrays["next_round"]), arrays["T_world_scan"], record["rounds"],
                           _labels_from(arrays, "labels_initial"), _labels_from(arrays, "labels_final"),
                           bool(arrays["frozen"]), record["unsettled_association"], fixed_point,
                           arrays.get("association_change"), _edge_labels_from(arrays, "edge_labels"))

    def save_carry(self, carry: RoundsCarry) -> None:
        """Keep what the next round starts from; it replaces the carry of the round before. The file is written on
        a thread of its own while the next round runs (the per-point labels are most of it: 8 bytes a point), from
        what the carry holds now: the poses, the records and the fixed point are copied here, the
        labels are never changed once made. `wait` waits for it; a carry still being written when the next one
        comes is finished first."""
        self.wait()
        record_json = json.dumps({"rounds": carry.records, "unsettled_association": carry.unsettled_association},
                                 default=json_value)
        arrays = {"next_round": np.array(carry.next_round), "T_world_scan": np.array(carry.T_world_scan),
                  "frozen": np.array(carry.frozen),
                  **{f"fixed_point_{key}": np.array(value) for key, value in carry.fixed_point.items()},
                  **({} if carry.association_change is None else
                     {"association_change": np.array(carry.association_change)})}

        def write() -> None:
            self._write("round", {**arrays, **_labels_arrays(carry.labels_initial, "labels_initial"),
                                  **_labels_arrays(carry.labels_final, "labels_final"),
                                  **_edge_labels_arrays(carry.edge_labels, "edge_labels")}, record_json)

        writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pa-work-folder")
        self._pending = writer.submit(write)
        writer.shutdown(wait=False)  # its thread ends with the write

    def wait(self) -> None:
        """Wait for a carry being written (`save_carry`); its error, if any, is raised here."""
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def drain(self) -> None:
        """Wait for a carry being written, without raising its error (a run that stops leaves the carry whole)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            futures_wait([pending])

    def remove(self) -> None:
        """Delete the folder and everything in it, once a carry being written is done."""
        self.drain()
        shutil.rmtree(self.path, ignore_errors=True)


def _labels_arrays(labels: PointLabels | None, name: str) -> dict[str, np.ndarray]:
    """`labels` as flat arrays under `name`_*: the observations' planes and scans, and every
    scan's point labels concatenated with the count per scan (nothing for None)."""
    if labels is None:
        return {}
    return {f"{name}_plane_index": labels.plane_index, f"{name}_scan_index": labels.scan_index,
            f"{name}_n_scans": np.array(labels.n_scans),
            f"{name}_points_per_scan": np.array([len(obs) for obs in labels.observation_of_point], dtype=np.int64),
            f"{name}_observation_of_point": np.concatenate(labels.observation_of_point)}


def _labels_from(arrays: dict[str, np.ndarray], name: str) -> PointLabels | None:
    """The `PointLabels` `_labels_arrays` flattened under `name` (None when absent)."""
    if f"{name}_plane_index" not in arrays:
        return None
    ends = np.cumsum(arrays[f"{name}_points_per_scan"])
    per_scan = np.split(arrays[f"{name}_observation_of_point"], ends[:-1])
    return PointLabels(arrays[f"{name}_plane_index"], arrays[f"{name}_scan_index"], int(arrays[f"{name}_n_scans"]),
                       per_scan)


def _edge_labels_arrays(edges: EdgeLabels | None, name: str) -> dict[str, np.ndarray]:
    """`edges` as flat arrays under `name`_*: its labels (`_labels_arrays`), the indices of its points in their
    scans, its shifts and the number of lines detected (nothing for None)."""
    if edges is None:
        return {}
    return {**_labels_arrays(edges.labels, name), f"{name}_point_index": np.concatenate(edges.point_index),
            f"{name}_shift_scan_m": edges.shift_scan_m, f"{name}_n_detected": np.array(edges.n_detected)}


def _edge_labels_from(arrays: dict[str, np.ndarray], name: str) -> EdgeLabels | None:
    """The `EdgeLabels` `_edge_labels_arrays` flattened under `name` (None when absent)."""
    labels = _labels_from(arrays, name)
    if labels is None:
        return None
    ends = np.cumsum([len(obs) for obs in labels.observation_of_point])
    return EdgeLabels(labels, np.split(arrays[f"{name}_point_index"], ends[:-1]), arrays[f"{name}_shift_scan_m"],
                      int(arrays[f"{name}_n_detected"]))


def open_work_folder(path: Path, expected: dict[str, Any], resume: bool, force: bool) -> WorkFolder:
    """The work folder at `path` for the inputs of `expected` (`manifest`). A new folder is made
    when there is none; an existing one is continued with `resume` (refused when made for other
    inputs), removed and made afresh with `force`, else refused."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"{path} is a file; the work folder of this run goes there. Move it or choose another --out.")
    if path.exists() and resume:
        manifest_path = path / MANIFEST
        try:
            found = json.loads(manifest_path.read_text())
        except (OSError, ValueError) as exc:
            raise InputError(f"{manifest_path}: expected the work folder's manifest ({exc}); run again without "
                             "--resume and with --force to start over.") from exc
        different = _differences(found, expected)
        if different:
            raise InputError(f"{path}: this work folder was made for other inputs ({', '.join(different)} differ); "
                             "run again with the inputs it was made for, or without --resume and with --force to "
                             "start over.")
        log.info("resuming from the finished stages in %s", path)
        return WorkFolder(path)
    if path.exists() and not force:
        raise OutputError(f"{path}: a work folder of an earlier run of this command is here; add --resume to "
                          "continue it from its last finished stage, or --force to start over.")
    if path.exists():
        shutil.rmtree(path)
    if resume:
        log.info("nothing to resume (no %s): starting from the beginning", path)
    path.mkdir()
    write_text_atomic(path / MANIFEST, json.dumps(expected, indent=2) + "\n")
    return WorkFolder(path)
