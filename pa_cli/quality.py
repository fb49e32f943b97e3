"""An honest verdict on a refinement: is the map really better than with the initial poses?

A refinement's own cost is measured on planes it found at its own poses, which favours them: a
broken trajectory can fit its own planes perfectly. The verdict therefore combines:

1. Cross-scored sharpness. Two plane associations are fixed per point: the one found at the
   INITIAL poses (round 1) and the one found at the REFINED poses (the last association). Both
   pose sets are scored on both (each with the points deskewed by its own trajectory): the RMS
   point-to-plane distance sqrt(sum of squared distances / points), planes at their best fit.
   The refined poses must be sharper on both.
2. Odometry consistency. Each consecutive pair's relative motion after refinement is compared
   with the initial one, in units of the odometry model's sigmas (rotation and translation
   separately); pairs changed by more than `quality_outlier_sigma` are listed: either the
   odometry broke there or the refinement did.
3. Ties. Two consecutive scans are tied by the map in the directions spanned by the normals of
   the landmarks they share: with M = sum of n n^T over those normals (unit, world frame), its
   middle eigenvalue below `quality_min_tie` means they share planes of one orientation only
   (e.g. the ground): rotation about that normal and sliding along the planes rest on the
   odometry alone, so a break of the initial trajectory there (a wrong turn) could be neither
   seen nor corrected.
4. Settling: whether the last round moved no pose more than the tolerance.

Verdict: `degraded` when the refined RMS is worse than the initial by more than
`quality_rms_tolerance` (relative) on either association; `improved` when it is better on both
and none of 2-4 raised a doubt; `uncertain` otherwise. `reasons` says why, in words.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pa_cli.problem import FeatureProblem


def rms_point_to_plane(problem: FeatureProblem, T_world_scan: np.ndarray) -> float:
    """sqrt(plane cost / points) (m) of a problem at poses T_world_scan."""
    from pa_cli.adjust import plane_cost

    return float(np.sqrt(plane_cost(problem, T_world_scan) / max(problem.n_points, 1)))


def pair_ties(problem: FeatureProblem, T_world_scan: np.ndarray) -> np.ndarray:
    """(N-1,) middle eigenvalue of sum n n^T over the landmarks scans j and j+1 both observe."""
    from pa_cli.planes.associate import world_plane_stats

    normals = world_plane_stats(problem, T_world_scan)[1]
    seen = np.zeros((problem.n_scans, max(problem.n_planes, 1)))
    seen[problem.scan_index, problem.plane_index] = 1.0
    shared = seen[:-1] * seen[1:]  # (N-1, P)
    M = np.einsum("jp,pa,pb->jab", shared, normals, normals)
    return np.linalg.eigvalsh(M)[:, 1]


def _pairs(indices: np.ndarray) -> list[list[int]]:
    return [[int(j), int(j) + 1] for j in indices]


def _list(pairs: list[list[int]], limit: int = 8) -> str:
    text = ", ".join(f"{a}-{b}" for a, b in pairs[:limit])
    return text + (" ..." if len(pairs) > limit else "")


def assess(rms: dict[str, dict[str, float]], odometry_sigmas: np.ndarray | None, ties: np.ndarray,
           settled: bool, outlier_sigma: float, min_tie: float, rms_tolerance: float) -> dict[str, Any]:
    """The `quality` report section.

    `rms[association][pose_set]` (m) for associations `planes_at_initial_poses`,
    `planes_at_refined_poses` and pose sets `initial`, `refined`; `odometry_sigmas` (N-1, 2):
    the change of each pair's relative rotation and translation in odometry sigmas (None: no
    factors); `ties` (N-1,): `pair_ties` of consecutive scans.
    """
    reasons: list[str] = []
    worse = [a for a, r in rms.items() if r["refined"] > r["initial"] * (1.0 + rms_tolerance)]
    not_better = [a for a, r in rms.items() if not r["refined"] < r["initial"]]
    for a in not_better:
        r = rms[a]
        reasons.append(f"RMS point-to-plane on the {a.replace('_', ' ')} is {r['refined']:.4f} m refined "
                       f"against {r['initial']:.4f} m initial: the refined map is not sharper there")
    disagree: list[list[int]] = []
    worst = None
    if odometry_sigmas is not None and len(odometry_sigmas):
        beyond = np.flatnonzero(odometry_sigmas.max(axis=1) > outlier_sigma)
        disagree = _pairs(beyond)
        worst = float(odometry_sigmas.max())
        if len(beyond):
            reasons.append(f"{len(beyond)} consecutive pair(s) changed their relative motion by more than "
                           f"{outlier_sigma:g} odometry sigmas (up to {worst:.1f}; pairs {_list(disagree)}): "
                           "the odometry or the refinement is wrong there")
    weak = np.flatnonzero(ties < min_tie)
    untied = _pairs(weak)
    if len(weak):
        reasons.append(f"{len(weak)} consecutive pair(s) share planes of one orientation only (pairs "
                       f"{_list(untied)}): the map does not tie them, their relative heading and sliding along "
                       "those planes rest on the odometry alone (a break there would go unseen)")
    if not settled:
        reasons.append("the rounds did not settle: the last round still moved a pose more than the tolerance")
    if worse:
        verdict = "degraded"
    elif reasons:
        verdict = "uncertain"
    else:
        verdict = "improved"
        reasons.append("the refined poses give a sharper map on planes found at the initial and at the refined "
                       "poses, agree with the odometry within its model, and the rounds settled")
    return {
        "verdict": verdict,
        "reasons": reasons,
        "rms_point_to_plane_m": rms,
        "odometry_outlier_sigma": outlier_sigma,
        "pairs_beyond_odometry_sigma": disagree,
        "n_scans_beyond_odometry_sigma": len({j for pair in disagree for j in pair}),
        "max_odometry_change_sigma": worst,
        "min_pair_tie": float(ties.min()) if len(ties) else None,
        "pairs_not_tied_by_planes": untied,
        "settled": bool(settled),
    }


def verdict_warning(quality: dict[str, Any] | None) -> str | None:
    """The end-of-run warning for a verdict other than `improved` (None when improved or absent)."""
    if not quality or quality["verdict"] == "improved":
        return None
    lines = [f"WARNING: quality verdict '{quality['verdict'].upper()}' - do not trust the refined poses blindly:"]
    lines += [f"  - {reason}" for reason in quality["reasons"]]
    lines.append("  (see 'quality' in the report; --strict turns this into exit code 1)")
    return "\n".join(lines)
