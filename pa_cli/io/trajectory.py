"""Trajectories: KITTI and TUM pose files.

Pose convention everywhere in `pa`: pose k is T_world_scan(k), the 4x4 rigid transform that
maps points of scan k (sensor frame) into the world frame. Units: metres and seconds.

- KITTI: 12 numbers per row, the top 3x4 of T_world_scan, row-major.
- TUM: `t tx ty tz qx qy qz qw` per row (t in seconds, quaternion Hamilton, scalar last).

Lines starting with `#` are skipped (whatever their encoding); data lines must be ASCII numbers.
One rule for the rotation of every pose, KITTI or TUM: a KITTI rotation block is projected onto
the nearest rotation (SVD) and a TUM quaternion is normalised; the deviation (Frobenius norm of
R - nearest rotation, or |quaternion norm - 1|) above `ORTHO_WARN` (1e-3) gives a warning naming
the worst pose, above `ORTHO_ERROR` (0.1) an error. Files are written in fixed point (`%.9f`)
and atomically.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pa_cli.core.geometry import orthonormalize
from pa_cli.errors import FormatError
from pa_cli.io.atomic import atomic_path
from pa_cli.io.files import read_input_bytes

log = logging.getLogger(__name__)

TrajectoryFormat = Literal["kitti", "tum"]
ORTHO_WARN = 1e-3
ORTHO_ERROR = 0.1


@dataclass
class Trajectory:
    """Poses T_world_scan (N, 4, 4) float64, with timestamps (N,) in seconds when known.

    `source` names where the poses came from (the file, for messages), or None.
    """

    T_world_scan: np.ndarray
    timestamps: np.ndarray | None = None
    source: str | None = None

    def __len__(self) -> int:
        return len(self.T_world_scan)


def _read_text_lines(path: Path, what: str) -> list[bytes]:
    """The lines of a text input file as bytes; missing, unreadable and binary files are errors."""
    raw = read_input_bytes(path, what)
    if b"\0" in raw:
        lineno = raw[:raw.index(b"\0")].count(b"\n") + 1
        raise FormatError(f"{path}:{lineno}: binary content (a NUL byte); expected a text {what} file.")
    return raw.splitlines()


def check_rotation_deviation(source: str | Path, deviation: np.ndarray, what: str, action: str, fix: str) -> None:
    """The rule for every pose's rotation: `deviation` (N,) of each pose from a rotation above
    `ORTHO_WARN` logs `action` with the worst pose, above `ORTHO_ERROR` raises a `FormatError`
    naming `source`, the pose and `fix`."""
    if not len(deviation):
        return
    worst = int(np.argmax(deviation))
    if deviation[worst] > ORTHO_ERROR:
        raise FormatError(f"{source}: pose {worst} {what} {deviation[worst]:.3g} > {ORTHO_ERROR}, so it is "
                          f"not a rotation; {fix}.")
    if deviation[worst] > ORTHO_WARN:
        log.warning("%s: %s (largest deviation %.3g > %g at pose %d).", source, action, deviation[worst],
                    ORTHO_WARN, worst)


def rigid_rotations(source: str | Path, R: np.ndarray, fix: str) -> np.ndarray:
    """The nearest rotations of (N, 3, 3) blocks, after the deviation check of this module
    (warning above `ORTHO_WARN`, `FormatError` naming `source` and the pose above `ORTHO_ERROR`)."""
    R_ortho, deviation = orthonormalize(R)
    check_rotation_deviation(source, deviation, "has a rotation block that deviates from a rotation by",
                             "rotations re-orthonormalised", fix)
    return R_ortho


def _load_rows(path: Path, what: str = "trajectory") -> np.ndarray:
    rows = []
    ncols = None
    for lineno, raw_line in enumerate(_read_text_lines(path, what), start=1):
        line = raw_line.strip()
        if not line or line.startswith(b"#"):
            continue
        parts = line.replace(b",", b" ").split()
        try:
            values = [float(v) for v in parts]
        except ValueError:
            shown = line[:60].decode("ascii", errors="replace")
            raise FormatError(
                f"{path}:{lineno}: non-numeric value in '{shown}'; expected KITTI (12 numbers) or TUM "
                "(8 numbers: t tx ty tz qx qy qz qw) rows, and '#' before comments."
            ) from None
        if ncols is None:
            ncols = len(values)
        elif len(values) != ncols:
            raise FormatError(
                f"{path}:{lineno}: {len(values)} columns, but earlier rows have {ncols}; "
                "every row must have the same number of columns."
            )
        rows.append(values)
    if not rows:
        raise FormatError(f"{path}: no poses found (empty file or only comments).")
    data = np.asarray(rows, dtype=np.float64)
    if not np.all(np.isfinite(data)):
        bad = int(np.argwhere(~np.isfinite(data))[0, 0])
        raise FormatError(f"{path}: pose {bad} contains NaN or inf values.")
    return data


def detect_format(ncols: int, path: Path) -> TrajectoryFormat:
    if ncols == 12:
        return "kitti"
    if ncols == 8:
        return "tum"
    raise FormatError(
        f"{path}: rows have {ncols} columns; expected 12 (KITTI: top 3x4 of T_world_scan) or "
        "8 (TUM: t tx ty tz qx qy qz qw)."
    )


def read_trajectory(path: Path | str, fmt: TrajectoryFormat | None = None) -> Trajectory:
    """Read a KITTI or TUM file; the format is detected by column count unless `fmt` is given."""
    path = Path(path)
    data = _load_rows(path)
    ncols = data.shape[1]
    detected = detect_format(ncols, path) if fmt is None else fmt
    expected = {"kitti": 12, "tum": 8}[detected]
    if ncols != expected:
        raise FormatError(
            f"{path}: rows have {ncols} columns but --format {detected} expects {expected}; "
            "drop --format to detect the format from the column count."
        )
    n = len(data)
    T = np.tile(np.eye(4), (n, 1, 1))
    timestamps = None
    if detected == "kitti":
        T[:, :3, :4] = data.reshape(n, 3, 4)
    else:
        timestamps = data[:, 0].copy()
        quat = data[:, 4:8]
        norms = np.linalg.norm(quat, axis=1)
        if np.any(norms < 1e-9):
            bad = int(np.argmin(norms))
            raise FormatError(f"{path}: pose {bad} has a zero quaternion.")
        check_rotation_deviation(path, np.abs(norms - 1.0), "has quaternion norm deviating from 1 by",
                         "quaternions normalised", "a TUM row is t tx ty tz qx qy qz qw with a unit quaternion")
        from scipy.spatial.transform import Rotation  # imported on use: scipy.spatial is slow to import

        T[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
        T[:, :3, 3] = data[:, 1:4]
        if np.any(np.diff(timestamps) <= 0):
            log.warning("%s: TUM timestamps are not strictly increasing.", path)
    T[:, :3, :3] = rigid_rotations(path, T[:, :3, :3], "check the file's format")
    return Trajectory(T_world_scan=T, timestamps=timestamps, source=str(path))


def read_timestamps(path: Path | str) -> np.ndarray:
    """Read one timestamp per line (seconds), `#` comments skipped."""
    data = _load_rows(Path(path), "timestamps")
    if data.shape[1] != 1:
        raise FormatError(f"{path}: expected one timestamp per line, found {data.shape[1]} columns.")
    return data[:, 0]


def format_kitti(T_world_scan: np.ndarray) -> str:
    rows = np.asarray(T_world_scan)[:, :3, :4].reshape(-1, 12)
    return "".join(" ".join(f"{v:.9f}" for v in row) + "\n" for row in rows)


def format_tum(T_world_scan: np.ndarray, timestamps: np.ndarray) -> str:
    from scipy.spatial.transform import Rotation  # imported on use: scipy.spatial is slow to import

    T = np.asarray(T_world_scan)
    quat = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    data = np.column_stack([timestamps, T[:, :3, 3], quat])
    return "".join(" ".join(f"{v:.9f}" for v in row) + "\n" for row in data)


def write_kitti(path: Path | str, T_world_scan: np.ndarray, force: bool = False) -> None:
    """Write poses as KITTI rows (top 3x4 of T_world_scan, %.9f), atomically."""
    with atomic_path(path, force) as tmp:
        tmp.write_text(format_kitti(T_world_scan))


def write_tum(path: Path | str, T_world_scan: np.ndarray, timestamps: np.ndarray | None,
              force: bool = False) -> None:
    """Write poses as TUM rows; without timestamps the frame index is used, with a warning."""
    if timestamps is None:
        log.warning("%s: no timestamps known; writing the frame index as the TUM time.", path)
        timestamps = np.arange(len(T_world_scan), dtype=np.float64)
    with atomic_path(path, force) as tmp:
        tmp.write_text(format_tum(T_world_scan, np.asarray(timestamps, dtype=np.float64)))


def write_trajectory(path: Path | str, trajectory: Trajectory, fmt: TrajectoryFormat,
                     force: bool = False) -> None:
    if fmt == "kitti":
        write_kitti(path, trajectory.T_world_scan, force)
    else:
        write_tum(path, trajectory.T_world_scan, trajectory.timestamps, force)
