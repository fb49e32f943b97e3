"""Motion compensation: move every point of a scan to the scan's reference instant.

A spinning LiDAR fires its columns over one sweep (0.1 s at 10 Hz) while the platform moves;
each point is measured in the sensor frame at its own firing time. When a scan carries
per-point times, `deskew_scan` moves each point into the sensor frame at the scan's
reference instant, using a continuous-time trajectory built from the scan poses.

Reference instant (the instant at which pose k, T_world_scan(k), is defined):
- a source that reads its time field itself (a ROS bag, `pa_cli.sources.base.DescribesTimeField`):
  the scan's earliest point, whatever the driver's convention; its times count from there;
- relative per-point times of a scan folder (within one sweep of 0 after unit detection): time
  0 of the field. For fields counted from the sweep start (the simulator, Ouster `t`, Livox
  `offset_time`, most drivers' `time`) this is the sweep START; for fields counted backwards from
  the sweep end (negative times) it is the sweep end;
- absolute per-point times of a scan folder: the scan's earliest point (the sweep start); that
  time is then also the scan's timestamp when no other timestamps are known.

Time unit rule (`pa_cli.sources.point_times.detect_time_unit`): the raw values are in s, ms, us or
ns; the unit is the one that makes the median sweep span (max - min of a scan's raw times) fall in
[max_sweep_s / 1000, max_sweep_s) (`MAX_SWEEP_S`, 2 s). Times are absolute
when, in that unit, the earliest time of a scan lies further than max_sweep_s from 0 (e.g. UNIX
time); relative otherwise.

Re-binning (`DeskewedPoints`): each point is attached to the scan whose reference instant is
nearest to its own time (the late part of a sweep goes to the next scan) and moved into that
scan's frame, so every point is placed by the pose nearest in time.

Trajectory (`pose_at_times`): poses T_world_scan(k) at the scans' reference times t_k, joined
by a cubic Hermite (Catmull-Rom) curve through neighbouring scan poses. On the segment [t_a, t_b]
the rotation is R(t) = R_a Exp(phi(t)) and the position p(t), where phi and p are cubic Hermite
interpolants of phi_j = Log(R_a^T R_j) and p_j over the scans j = a-1 .. a+2, with tangents by
central differences (one-sided at the first and last scan). The curve passes through every pose
with continuous velocity, so a platform that sways (roll/pitch oscillating within a few scans)
is followed far better than by the geodesic between two poses. Before the first and after the last scan the
end velocity is kept (constant-velocity extrapolation). A point p measured at time t in scan k
becomes R_k^T (R(t) p + p(t) - p_k).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from pa_cli.core.geometry import exp_so3, log_so3, retract_left
from pa_cli.errors import InputError
from pa_cli.sources import PointsView
from pa_cli.sources.base import DescribesTimeField
from pa_cli.sources.point_times import TimeUnit, detect_time_unit, sweep_times_s

# Longest sweep (s) the time-unit detection accepts (the unit puts the median sweep span in
# [MAX_SWEEP_S / 1000, MAX_SWEEP_S)): spinning LiDARs sweep in 0.05-0.2 s, far inside that window.
MAX_SWEEP_S = 2.0


def relative_times_s(raw_time: np.ndarray, unit: TimeUnit) -> tuple[np.ndarray, float]:
    """Per-point times (s) relative to the scan's reference instant, and that instant (s).

    Relative fields: the reference is the field's 0 (returned as 0.0). Absolute fields: the
    scan's earliest point; the returned instant is its absolute time (s), computed in the raw
    unit (`sweep_times_s`).
    """
    if not unit.absolute:
        return np.asarray(raw_time).astype(np.float64) * unit.seconds_per_unit, 0.0
    return sweep_times_s(raw_time, unit, 0.0)


def _check_trajectory(stamps_s: np.ndarray, T_world_scan: np.ndarray) -> None:
    if len(stamps_s) != len(T_world_scan) or len(stamps_s) < 2:
        raise InputError(f"deskew: {len(stamps_s)} scan times for {len(T_world_scan)} poses; "
                         "a trajectory needs one time per pose and at least two poses.")
    if np.any(np.diff(stamps_s) <= 0):
        raise InputError("deskew: scan times are not strictly increasing; check times.txt or the "
                         "TUM timestamps of --poses.")


def _hermite(x_a: np.ndarray, x_b: np.ndarray, m_a: np.ndarray, m_b: np.ndarray, h: np.ndarray,
             s: np.ndarray) -> np.ndarray:
    """Cubic Hermite interpolant for s in [0, 1] (values x (M, 3), tangents m (M, 3) per second,
    segment lengths h (M,) s); outside [0, 1] the end value plus the end tangent (constant velocity)."""
    sc = np.clip(s, 0.0, 1.0)[:, None]
    s2, s3 = sc * sc, sc * sc * sc
    x = ((2 * s3 - 3 * s2 + 1) * x_a + (s3 - 2 * s2 + sc) * h[:, None] * m_a
         + (-2 * s3 + 3 * s2) * x_b + (s3 - s2) * h[:, None] * m_b)
    x = np.where((s < 0.0)[:, None], x_a + (s * h)[:, None] * m_a, x)
    return np.where((s > 1.0)[:, None], x_b + ((s - 1.0) * h)[:, None] * m_b, x)


def _parabola_slope(t0: np.ndarray, t1: np.ndarray, t2: np.ndarray, x0: np.ndarray, x1: np.ndarray,
                    x2: np.ndarray) -> np.ndarray:
    """Slope at t0 of the parabola through (t0, x0), (t1, x1), (t2, x2) (three distinct times)."""
    w0 = (2 * t0 - t1 - t2) / ((t0 - t1) * (t0 - t2))
    w1 = (t0 - t2) / ((t1 - t0) * (t1 - t2))
    w2 = (t0 - t1) / ((t2 - t0) * (t2 - t1))
    return w0[:, None] * x0 + w1[:, None] * x1 + w2[:, None] * x2


def _hermite_through(values: list[np.ndarray], t: list[np.ndarray], s: np.ndarray) -> np.ndarray:
    """Catmull-Rom on segment [1, 2] of four samples (values, times; at the first or last scan a
    neighbour repeats an end sample). Tangents: central differences inside; at an end, the slope
    of the parabola through the three samples there (second order, so constant-velocity
    extrapolation past the last scan starts from the right velocity)."""
    m_a = (values[2] - values[0]) / (t[2] - t[0])[:, None]
    m_b = (values[3] - values[1]) / (t[3] - t[1])[:, None]
    first = (t[0] == t[1]) & (t[3] > t[2])
    last = (t[3] == t[2]) & (t[0] < t[1])
    if np.any(first):
        m_a[first] = _parabola_slope(t[1][first], t[2][first], t[3][first],
                                     values[1][first], values[2][first], values[3][first])
    if np.any(last):
        m_b[last] = _parabola_slope(t[2][last], t[1][last], t[0][last],
                                    values[2][last], values[1][last], values[0][last])
    return _hermite(values[1], values[2], m_a, m_b, t[2] - t[1], s)


def pose_at_times(stamps_s: np.ndarray, T_world_scan: np.ndarray, times_s: np.ndarray) -> np.ndarray:
    """T_world_sensor (M, 4, 4) at times_s (s, same clock as stamps_s), see the module docstring."""
    stamps_s = np.asarray(stamps_s, dtype=np.float64)
    _check_trajectory(stamps_s, T_world_scan)
    times_s = np.asarray(times_s, dtype=np.float64)
    n = len(stamps_s)
    a = np.clip(np.searchsorted(stamps_s, times_s, side="right") - 1, 0, n - 2)
    neighbours = (np.maximum(a - 1, 0), a, a + 1, np.minimum(a + 2, n - 1))
    t = [stamps_s[j] for j in neighbours]
    s = (times_s - t[1]) / (t[2] - t[1])
    R = T_world_scan[:, :3, :3]
    R_a_T = R[a].transpose(0, 2, 1)
    phi = [Rotation.from_matrix(R_a_T @ R[j]).as_rotvec() for j in neighbours]  # tangent space at R_a
    out = np.zeros((len(times_s), 4, 4))
    out[:, :3, :3] = R[a] @ Rotation.from_rotvec(_hermite_through(phi, t, s)).as_matrix()
    out[:, :3, 3] = _hermite_through([T_world_scan[j, :3, 3] for j in neighbours], t, s)
    out[:, 3, 3] = 1.0
    return out


def deskew_scan(points_scan: np.ndarray, point_time_s: np.ndarray, k: int, stamps_s: np.ndarray,
                T_world_scan: np.ndarray) -> np.ndarray:
    """Points of scan k (M, 3, sensor frame at their own times) moved to scan k's reference instant.

    `point_time_s` (M,) are seconds relative to that instant (`relative_times_s`), `stamps_s`
    (N,) the reference instants of all scans and `T_world_scan` (N, 4, 4) the poses there.
    Points are grouped by their distinct times (the columns of a sweep), so the trajectory is
    evaluated once per column, not once per point.
    """
    points_scan = np.asarray(points_scan, dtype=np.float64)
    if len(points_scan) == 0:
        return points_scan
    unique_t, inverse = np.unique(np.asarray(point_time_s, dtype=np.float64), return_inverse=True)
    T_t = pose_at_times(stamps_s, T_world_scan, stamps_s[k] + unique_t)
    T_k_inv = np.linalg.inv(T_world_scan[k])
    T_rel = T_k_inv[None] @ T_t  # (U, 4, 4): sensor at time t -> sensor at the reference instant
    R = T_rel[inverse, :3, :3]
    return np.einsum("mij,mj->mi", R, points_scan) + T_rel[inverse, :3, 3]


def stamps_from_sweeps(n_scans: int, sweep_span_s: np.ndarray) -> np.ndarray:
    """Scan reference times (s) when none are known: consecutive sweeps, k * median sweep span.

    Assumes one scan per sweep with no gaps (a spinning LiDAR's driver output); give
    `times.txt` or TUM `--poses` otherwise.
    """
    span = np.asarray(sweep_span_s, dtype=np.float64)
    span = span[np.isfinite(span) & (span > 0)]
    if len(span) == 0:
        raise InputError("deskew: no scan has a time span; cannot derive scan times from sweeps.")
    return np.arange(n_scans) * float(np.median(span))


class DeskewedPoints(Sequence):
    """Scans re-binned by time and motion-compensated: item j holds every point measured nearer
    in time to scan j's reference instant than to any other scan's, in the sensor frame at that
    instant.

    A sweep lasts a whole scan period, so the late part of scan k is measured closer to the
    instant of scan k+1 than to its own. Attaching each point to the pose nearest in time keeps
    the rigid-scan model of the adjustment close to the continuous trajectory (every point lies
    within half a period of its pose, and that pose carries at least half of its interpolation
    weight); deskewing scan k's late points into scan k's frame instead lets them follow the
    next pose, and re-deskewing with the adjusted poses then feeds changes back between
    neighbours. The binning depends on the times only, so every round sees the same points
    in the same order.

    `raw_points[k]` (M_k, 3) and `point_times_s[k]` (M_k,) (relative to scan k's reference
    instant, or None: the scan is kept as it is and nothing is moved in or out of it).
    `at(T_world_scan)` gives the same scans motion-compensated with another trajectory.
    """

    def __init__(self, raw_points: Sequence[np.ndarray], point_times_s: Sequence[np.ndarray | None],
                 stamps_s: np.ndarray, T_world_scan: np.ndarray) -> None:
        self.raw_points = raw_points
        self.point_times_s = point_times_s
        self.stamps_s = np.asarray(stamps_s, dtype=np.float64)
        _check_trajectory(self.stamps_s, T_world_scan)
        self.T_world_scan = np.array(T_world_scan, dtype=np.float64, copy=True)
        n = len(raw_points)
        self._parts: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(n)]
        timed = [k for k in range(n) if point_times_s[k] is not None]
        midpoints = 0.5 * (self.stamps_s[1:] + self.stamps_s[:-1])
        for k in range(n):
            if point_times_s[k] is None:
                self._parts[k].append((k, np.arange(len(raw_points[k]))))
                continue
            target = np.searchsorted(midpoints, self.stamps_s[k] + np.asarray(point_times_s[k], np.float64))
            allowed = np.isin(target, timed)  # scans without times keep their own points only
            target = np.where(allowed, target, k)
            for j in np.unique(target):
                self._parts[int(j)].append((k, np.flatnonzero(target == j)))

    def at(self, T_world_scan: np.ndarray) -> DeskewedPoints:
        """These scans motion-compensated with the trajectory T_world_scan (points and binning shared)."""
        _check_trajectory(self.stamps_s, T_world_scan)
        view = copy.copy(self)
        view.T_world_scan = np.array(T_world_scan, dtype=np.float64, copy=True)
        return view

    def __len__(self) -> int:
        return len(self.raw_points)

    def sources(self, j: int) -> list[tuple[int, np.ndarray]]:
        """(raw scan k, point indices in it) of item j's points, in the order item j returns them
        (its own scan first)."""
        return sorted(self._parts[j], key=lambda part: part[0] != j)

    def parts(self, j: int) -> list[tuple[int, np.ndarray, np.ndarray | None]]:
        """Item j by the scan that measured its points: (k, points in scan j's frame at its
        reference instant (M, 3), their times relative to scan k's reference instant (M,) s or None),
        in the order of `sources(j)`."""
        out = []
        for k, index in self.sources(j):
            points = np.asarray(self.raw_points[k], dtype=np.float64)[index]
            times = self.point_times_s[k]
            if times is None:
                out.append((k, points, None))
                continue
            own_s = np.asarray(times, dtype=np.float64)[index]
            offset_s = self.stamps_s[k] + own_s - self.stamps_s[j]
            out.append((k, deskew_scan(points, offset_s, j, self.stamps_s, self.T_world_scan), own_s))
        return out

    def __getitem__(self, j):  # type: ignore[override]
        pieces = [points for _, points, _ in self.parts(j)]
        return np.vstack(pieces) if pieces else np.empty((0, 3))


class TimedScans:
    """Every scan's points (sensor frame at their own times, read through the scan source and its
    point cache) and per-point times (s, float32, relative to the scan's reference instant), read
    once from the source (`pa_cli.sources.ScanSource`: `points(k)`, `point_times(k)`).

    `unit` is the detected time unit (None: no scan has a usable time field); `reference_s`
    holds each scan's reference instant on the points' clock for absolute time fields (else
    None). A scan without a time field gets times None (it is used as it is). `field` is how the
    source read its time field (`DescribesTimeField`; None for a scan folder); `problem` says
    why there are no usable times (None when there are) and `suspect` whether a field that looks
    like a time was found but not used (a reason to warn).
    """

    def __init__(self, source: Any) -> None:
        self.points = PointsView(source)  # read through the source (and its point cache), not copied
        self.field = source.time_field() if isinstance(source, DescribesTimeField) else None
        raw_times: list[np.ndarray | None] = []
        for k in range(len(source)):
            n_points, times = len(source.points(k)), source.point_times(k)
            raw_times.append(None if times is None or len(times) != n_points else np.asarray(times))
        have = [t for t in raw_times if t is not None and len(t)]
        self.unit = detect_time_unit([t.min() for t in have], [t.max() for t in have], MAX_SWEEP_S) if have else None
        self.times_s: list[np.ndarray | None] = [None] * len(raw_times)
        reference = np.full(len(raw_times), np.nan)
        if self.unit is not None:
            for k, raw in enumerate(raw_times):
                if raw is not None and len(raw):
                    relative, reference[k] = relative_times_s(raw, self.unit)
                    self.times_s[k] = relative.astype(np.float32)
        self.n_with_times = sum(t is not None for t in self.times_s)
        self.reference_s = reference if self.unit is not None and self.unit.absolute else None
        spans = [float(t.max() - t.min()) for t in self.times_s if t is not None and len(t)]
        self.median_sweep_s = float(np.median(spans)) if spans else None
        self.problem, self.suspect = None, False
        if self.unit is None:
            if self.field is not None and self.field.problem is not None:
                self.problem, self.suspect = self.field.problem, bool(self.field.suspects)
            elif have:
                span = float(np.median([t.max() - t.min() for t in have]))
                self.problem, self.suspect = (f"the per-point times span {span:.6g} (raw units, median over the "
                                              "scans) and no unit of s, ms, us or ns puts that between "
                                              f"{MAX_SWEEP_S / 1000:g} and {MAX_SWEEP_S:g} s"), True
            else:
                self.problem = "no per-point time field (time, t, timestamp or offset_time)"

    def __len__(self) -> int:
        return len(self.points)

    def report(self) -> dict[str, Any]:
        """The report's `deskew` entries for the times read: the field as the source read it (its
        unit and reference instant), else the unit detected here from the raw values."""
        common = {"n_scans_with_times": self.n_with_times, "median_sweep_s": self.median_sweep_s}
        if self.field is not None and self.field.name is not None:
            return {"time_field": self.field.report(), "time_unit": self.field.unit,
                    "absolute_times": self.field.absolute, "reference_instant": self.field.reference, **common}
        return {"time_field": None, "time_unit": self.unit.name, "absolute_times": self.unit.absolute,
                "reference_instant": "earliest point of each scan" if self.unit.absolute else "time 0 of the field",
                **common}


def scan_reference_times(timed: TimedScans, known_stamps_s: np.ndarray | None) -> tuple[np.ndarray, str]:
    """Reference instants (s) of all scans on one clock, and where they came from.

    Absolute per-point times give them directly (every scan must then have times); else the
    known per-scan timestamps (times.txt, TUM --poses); else consecutive sweeps
    (`stamps_from_sweeps`)."""
    n = len(timed)
    if timed.reference_s is not None and np.all(np.isfinite(timed.reference_s)):
        return timed.reference_s, "absolute per-point times (earliest point of each scan)"
    if known_stamps_s is not None and len(known_stamps_s) == n and np.all(np.diff(known_stamps_s) > 0):
        return np.asarray(known_stamps_s, dtype=np.float64), "scan timestamps"
    spans = [float(t.max() - t.min()) for t in timed.times_s if t is not None and len(t)]
    return stamps_from_sweeps(n, np.asarray(spans)), "consecutive sweeps (k x median sweep span)"


def kiss_icp_pose_offsets_s(timed: TimedScans, kiss_deskew: bool) -> np.ndarray:
    """When, relative to each scan's reference instant (s), KISS-ICP's pose of that scan holds.

    With deskewing (kiss-icp 1.x) it moves every point to the END of the sweep (normalised
    stamp 1: its preprocessor applies Exp((s - 1) * motion)), so its pose is the pose at the
    scan's latest point time. Without deskewing it registers the raw sweep, whose points span
    the sweep: its least-squares pose is, to first order in the motion, the pose at the mean
    point time. Scans without times get 0 (taken as already at the reference instant).
    """
    offsets = np.zeros(len(timed))
    for k, t in enumerate(timed.times_s):
        if t is not None and len(t):
            offsets[k] = float(t.max()) if kiss_deskew else float(np.mean(t, dtype=np.float64))
    return offsets


def shift_in_time(T_world_scan: np.ndarray, stamps_s: np.ndarray, offsets_s: np.ndarray) -> np.ndarray:
    """Poses at stamps_s from poses that hold at stamps_s + offsets_s (same continuous-time
    trajectory as `pose_at_times`, through the given poses at their true instants)."""
    held_at = np.asarray(stamps_s, dtype=np.float64) + np.asarray(offsets_s, dtype=np.float64)
    return pose_at_times(held_at, T_world_scan, stamps_s)


def _chart(T_base: np.ndarray, T: np.ndarray, lever_arm_m: float) -> np.ndarray:
    """(N * 6,) coordinates of poses T around T_base in the chart of `retract_left`
    (T = retract_left(T_base, delta), delta = (omega rad, rho m)), omega scaled to metres by
    `lever_arm_m`, so that rotation and translation weigh alike in inner products."""
    omega = log_so3(np.einsum("nij,nkj->nik", T[:, :3, :3], T_base[:, :3, :3]))
    rho = T[:, :3, 3] - np.einsum("nij,nj->ni", exp_so3(omega), T_base[:, :3, 3])
    return np.hstack([omega * lever_arm_m, rho]).ravel()


class DeskewFixedPoint:
    """Acceleration of the deskew fixed point: the rounds with a frozen association.

    A frozen round is a map F: the trajectory x deskews the points, the adjustment on those
    points gives F(x); the refined trajectory is its fixed point x* = F(x*). Near x*, F is
    affine with Jacobian J, and the plain iteration x <- F(x) shrinks the error by J each round.
    Physically the error that survives a round is the trajectory's velocity error: it places
    the points of every sweep a little wrong, the adjustment absorbs only part of that into the
    poses, and what it leaves is the same smooth shape along the path, smaller by a nearly
    constant factor r (one dominant eigenvalue of J). A contraction r needs log(tol / d) /
    log(r) rounds to bring a change d under the tolerance - many when r is near 1.

    `next_start` makes the Anderson(1) (secant) step on the residual g(x) = F(x) - x from the
    last two rounds: x' = F(x_k) - gamma (F(x_k) - F(x_{k-1})), gamma = <dg, g_k> / <dg, dg>,
    dg = g_k - g_{k-1}, with inner products in the tangent chart of `retract_left` around
    F(x_k) (rotations scaled to metres by the lever arm). For a single mode of contraction r,
    -gamma = r / (1 - r) and x' is the fixed point exactly; the other modes contract as before.
    Safeguards, on the residual - the quantity the fixed point zeroes and the settle test
    measures (the self-consistent cost, the objective with the points deskewed by the same
    trajectory, is no merit function: the deskew's own derivative keeps it from being
    stationary at x*):
    - the step is taken only when the measured contraction r = -gamma / (1 - gamma) lies in
      (0, max_contraction]: an oscillating or diverging map is not extrapolated, and a
      contraction near 1 would extrapolate without bound;
    - when the round started from an extrapolated x' left a residual |g| no smaller than the
      round before it, the extrapolation failed: the next start is the plain F(x'), and the
      secant restarts from there.
    The round's output is always the adjustment's result: an extrapolated trajectory is only
    where the next round starts, and the rounds settle only when an adjustment moves no pose
    more than the tolerance from its start.
    """

    def __init__(self, lever_arm_m: float, max_contraction: float) -> None:
        self.lever_arm_m = float(lever_arm_m)
        self.max_contraction = float(max_contraction)
        self._last: tuple[np.ndarray, np.ndarray, float] | None = None  # x_{k-1}, F(x_{k-1}), |g_{k-1}|
        self._extrapolated = False  # whether x_k was extrapolated

    def memory(self) -> dict[str, np.ndarray]:
        """What `next_start` remembers of the rounds before, as arrays (`remember` takes it back)."""
        memory = {"extrapolated": np.array(self._extrapolated)}
        if self._last is not None:
            memory.update(start=self._last[0], result=self._last[1], residual_m=np.array(self._last[2]))
        return memory

    def remember(self, memory: dict[str, np.ndarray]) -> None:
        """Continue from `memory` (`DeskewFixedPoint.memory`; empty: from the start)."""
        self._extrapolated = bool(memory.get("extrapolated", False))
        self._last = (memory["start"], memory["result"], float(memory["residual_m"])) if "start" in memory else None

    def next_start(self, T_start: np.ndarray, T_result: np.ndarray) -> tuple[np.ndarray, dict]:
        """Where the next round starts after a round from `T_start` gave `T_result` (both
        (N, 4, 4)), and a record for the report: the residual's norm (m, rotations at the lever
        arm), the measured contraction (None when not measured), whether the next start is
        extrapolated and whether the last extrapolation failed."""
        g_k = -_chart(T_result, T_start, self.lever_arm_m)  # F(x_k) - x_k, F(x_k) at the chart's origin
        norm_k = float(np.linalg.norm(g_k))
        last, self._last = self._last, (T_start, T_result, norm_k)
        record: dict = {"residual_m": round(norm_k, 6), "contraction": None, "extrapolated": False}
        failed = self._extrapolated and last is not None and norm_k >= last[2]
        self._extrapolated = False
        if failed:
            record["extrapolation_failed"] = True
        if last is None or failed or self.max_contraction <= 0:
            return T_result, record
        a = _chart(T_result, last[0], self.lever_arm_m)  # x_{k-1}
        b = _chart(T_result, last[1], self.lever_arm_m)  # F(x_{k-1})
        dg = g_k - (b - a)
        dg2 = float(dg @ dg)
        if dg2 <= 0.0:
            return T_result, record
        gamma = float(dg @ g_k) / dg2
        contraction = -gamma / (1.0 - gamma)
        record["contraction"] = round(contraction, 4)
        if not 0.0 < contraction <= self.max_contraction:
            return T_result, record
        record["extrapolated"] = self._extrapolated = True
        return retract_left(T_result, (gamma * b).reshape(-1, 6) / np.array([self.lever_arm_m] * 3 + [1.0] * 3)), record
