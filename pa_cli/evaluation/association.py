"""Pairing the poses of two trajectories: by timestamp (nearest within a tolerance) or by index.

Pairs are returned in time order (the ground truth's timestamps), whatever the order of the
files, so relative errors are always taken between poses consecutive in time (as evo does).
A timestamp pairing that leaves many poses unpaired usually means the two files use
different clocks (e.g. an index written as time): below `WARN_PAIRED_FRACTION` it is
reported, below `MIN_PAIRED_FRACTION` it is refused.
"""

from __future__ import annotations

import logging

import numpy as np

from pa_cli.errors import InputError
from pa_cli.io.trajectory import Trajectory

log = logging.getLogger(__name__)

# Fractions of the shorter trajectory's poses that must find a partner by timestamp. An
# estimate that covers part of the ground truth pairs all of its poses; one that loses a
# few (dropped frames, edges of the recording) stays above 0.9. Below 0.9 the metrics
# describe only part of the run (warning); below 0.5 they describe a minority of it, which
# is nearly always a clock mismatch, so the evaluation is refused.
WARN_PAIRED_FRACTION = 0.9
MIN_PAIRED_FRACTION = 0.5


def match_timestamps(stamps_a: np.ndarray, stamps_b: np.ndarray, max_diff_s: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Pair each stamp of the shorter list with its nearest stamp in the other, within max_diff_s.

    Returns index arrays (ia, ib) into `stamps_a` and `stamps_b`, in the order of the shorter list.
    """
    a = np.asarray(stamps_a, dtype=np.float64)
    b = np.asarray(stamps_b, dtype=np.float64)
    swap = len(b) < len(a)
    short, long_ = (b, a) if swap else (a, b)
    order = np.argsort(long_, kind="stable")
    sorted_long = long_[order]
    pos = np.searchsorted(sorted_long, short)
    lo = np.clip(pos - 1, 0, len(long_) - 1)
    hi = np.clip(pos, 0, len(long_) - 1)
    d_lo = np.abs(sorted_long[lo] - short)
    d_hi = np.abs(sorted_long[hi] - short)
    best = np.where(d_hi < d_lo, hi, lo)
    diff = np.minimum(d_lo, d_hi)
    ok = diff <= max_diff_s
    i_short = np.flatnonzero(ok)
    i_long = order[best[ok]]
    return (i_long, i_short) if swap else (i_short, i_long)


def _name(trajectory: Trajectory, fallback: str) -> str:
    return trajectory.source if trajectory.source is not None else fallback


def pair_trajectories(gt: Trajectory, est: Trajectory, max_diff_s: float, min_pairs: int
                      ) -> tuple[np.ndarray, np.ndarray, str]:
    """Index arrays (i_gt, i_est) of paired poses, in time order, and the pairing ("timestamp"/"index").

    By timestamp (nearest within `max_diff_s` seconds) when both trajectories have timestamps,
    otherwise by index (then both must have the same length). Raises `InputError` when fewer
    than `min_pairs` poses pair, or fewer than `MIN_PAIRED_FRACTION` of the shorter
    trajectory's poses; warns below `WARN_PAIRED_FRACTION`.
    """
    n_gt, n_est = len(gt), len(est)
    gt_name, est_name = _name(gt, "the ground truth"), _name(est, "the estimate")
    if gt.timestamps is None or est.timestamps is None:
        if n_gt != n_est:
            raise InputError(
                f"{gt_name} has {n_gt} poses but {est_name} has {n_est}; without timestamps on both "
                "(TUM files) poses are paired by index, so the lengths must be equal."
            )
        if n_gt < min_pairs:
            raise InputError(f"{gt_name} and {est_name} have {n_gt} poses; at least {min_pairs} are needed.")
        return np.arange(n_gt), np.arange(n_gt), "index"
    i_gt, i_est = match_timestamps(gt.timestamps, est.timestamps, max_diff_s)
    order = np.argsort(gt.timestamps[i_gt], kind="stable")
    i_gt, i_est = i_gt[order], i_est[order]
    n_pairs, n_short = len(i_gt), min(n_gt, n_est)
    counts = (f"only {n_pairs} of the {n_short} poses of the shorter trajectory ({gt_name}: {n_gt} poses, "
              f"{est_name}: {n_est}) have a partner within {max_diff_s} s")
    if n_pairs < min_pairs:
        raise InputError(f"{counts}; at least {min_pairs} are needed. Check that both use the same clock, "
                         "or raise --max-diff.")
    if n_pairs < MIN_PAIRED_FRACTION * n_short:
        raise InputError(f"{counts}, below {MIN_PAIRED_FRACTION:.0%}; the timestamps of the two files do "
                         "not describe the same run. Check that both use the same clock (not an index as "
                         "time), or raise --max-diff.")
    if n_pairs < WARN_PAIRED_FRACTION * n_short:
        log.warning("%s, below %.0f%%; the metrics cover only the paired poses.", counts,
                    100 * WARN_PAIRED_FRACTION)
    return i_gt, i_est, "timestamp"
