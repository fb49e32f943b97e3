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
   separately); pairs changed by more than `advanced.quality.outlier_sigma` are listed: either the
   odometry broke there or the refinement did.
3. Ties. The landmarks two consecutive scans both observe tie their relative motion: their
   information on it (`pair_tie_information`: per shared landmark, the weaker observation's
   2 sum J J^T, J = [p x n; n]) is compared with the odometry factor's, direction by direction
   (`pair_ties`: the smallest generalised eigenvalue r). A break of the relative motion by k
   odometry sigmas along a direction raises the shared planes' cost by r k^2 sigma_point^2; with
   k = `advanced.quality.outlier_sigma`, a pair with r < 1 / k^2 would hide such a break (it would raise
   the cost by less than one sigma_point^2): its relative motion rests on the odometry alone, so a
   break of the initial trajectory there (a wrong turn) could be neither seen nor corrected.
   A pair whose change exceeds k odometry sigmas is a doubt only where its shared planes carry
   less information than the odometry along that change (`decided_by_planes`); elsewhere the
   planes corrected the odometry, which is stated, not doubted. Scans held by odometry in some
   direction (`pa_cli.evaluation.degeneracy`) are stated too: the planes still check those directions.
4. Settling: whether the last round moved no pose more than the tolerance.
5. Mean map entropy (MME), a sharpness measure that needs no planes: for a query point of the
   map, the differential entropy of a Gaussian fit to the map points within `radius_m` of it,
   h = 1/2 ln det(2 pi e Sigma) (nats); MME is its mean over the query points. A sharper map has
   thinner neighbourhoods, hence a smaller det Sigma and a lower MME; a difference of
   3 ln(1 + x) nats is every neighbourhood's standard deviations growing by a fraction x.
   Both pose sets are scored on the same points (the same subsample of every scan, each deskewed
   by its own trajectory) and the same query points (those with enough neighbours under both).
   The MME is also taken apart by the normal of each neighbourhood: upright surfaces (walls,
   poles, trunks) see the horizontal position and heading, level ones (ground, roofs) the height,
   roll and pitch. On a street whose ground dominates the map, a refinement can sharpen the ground
   a lot and blur the upright surfaces, and the overall MME still falls: neither class may get
   blurrier by more than `advanced.quality.entropy_tolerance_nats` and, beyond the chance of which points
   were queried, by more than `advanced.quality.entropy_standard_errors` standard errors of its mean change.

6. Free space (`pa_cli.evaluation.free_space`): the fraction of points of overlapping scans that
   lie in space another scan saw through (violations), under each pose set on the same pairs and
   points, with the standard error of the change; a violation lies deeper in front of another
   scan's return than the MME's radius, beyond what the MME sees. A map of two sharp copies (a
   broken start) lowers the MME and fills the other copy's free space.

The evidence is of two kinds. The RMS of 1 is measured on planes the adjustment fitted (round 1's
at the initial poses, the last round's at the refined ones); the MME of 5 and the free space of 6
look at every point and at the rays, which the adjustment never saw: the map-wide evidence. The
planes found at the initial poses carry the initial poses' imprint (their points were gathered
by gates around planes fitted to a blurred map), so their RMS alone is a fragile judge: it may rise
by a percent while the map is sharper everywhere.

Verdict: `degraded` when
- the refined MME is higher than the initial by more than `advanced.quality.entropy_tolerance_nats`, or
- the free-space violation fraction rose by more than FREE_SPACE_STANDARD_ERRORS standard errors
  of its change and to more than FREE_SPACE_DEGRADED_FACTOR times the initial one (ghost copies), or
- the refined RMS is worse than the initial by more than `advanced.quality.rms_tolerance` (relative)
  on the planes found at the refined poses, or on those found at the initial poses unless the
  map-wide evidence all improved: the MME lower, neither class of surfaces blurrier and the free
  space not worse (the RMS rise is then stated as a note).
`improved` when the RMS is better on both associations (or only the initial association's is
worse and the map-wide evidence all improved), the MME is lower, neither class of surfaces is
blurrier, the free space is not worse and none of 2-4 raised a doubt; `uncertain` otherwise (a
rise of the violation fraction beyond its standard errors but below the factor is a doubt).
`reasons` says why, in words, followed by the notes (corrections beyond the odometry model, held
directions, an RMS rise outvoted by the map-wide evidence).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pa_cli.adjust import plane_cost
from pa_cli.core.geometry import skew
from pa_cli.core.neighbourhoods import neighbourhood_fit
from pa_cli.core.problem import FeatureProblem
from pa_cli.planes.associate import world_plane_stats

# Floor on each standard deviation of a map-entropy neighbourhood (m), below the range noise of any
# LiDAR: a noise-free planar neighbourhood (simulated) keeps a finite entropy.
ENTROPY_MIN_SIGMA_M = 0.001


# The free-space violation fraction counts as risen beyond chance above this many standard errors of its change (the
# choice of pairs and points): 3 of them are exceeded about once in 740 draws.
FREE_SPACE_STANDARD_ERRORS = 3.0
# A refined violation fraction risen beyond chance to more than this many times the initial one is a degraded map:
# twice the initial poses' violations is a surface moved into the space other scans saw empty, which moving
# objects and noise (present under both pose sets) do not double.
FREE_SPACE_DEGRADED_FACTOR = 2.0
# how the reason of an `improved` verdict starts (`Quality.with_doubt` drops it)
IMPROVED_REASON = "the refined poses give a sharper map"


@dataclass
class Quality:
    """The verdict (`improved`, `uncertain`, `degraded`) and the evidence behind it (`assess`).

    `rms_point_to_plane_m[association][pose_set]` (m), `map_entropy` (`mean_map_entropy`'s
    result or None), `free_space` (`free_space_check`'s result or None), the consecutive pairs
    (`[j, j + 1]`) that changed beyond the odometry model where the planes did not decide the
    change, those the planes corrected, those their shared planes do not tie, and whether the
    rounds settled. `as_report()` is the report's section.
    """

    verdict: str
    reasons: list[str]
    rms_point_to_plane_m: dict[str, dict[str, float]]
    map_entropy: dict[str, Any] | None
    free_space: dict[str, Any] | None
    blurrier_surfaces: list[str]
    odometry_outlier_sigma: float
    pairs_beyond_odometry_sigma: list[list[int]]
    pairs_corrected_by_planes: list[list[int]]
    n_scans_beyond_odometry_sigma: int
    max_odometry_change_sigma: float | None
    min_pair_tie: float | None
    pairs_not_tied_by_planes: list[list[int]]
    settled: bool

    def as_report(self) -> dict[str, Any]:
        """The `quality` section of the refine report (the fields, in order)."""
        return dataclasses.asdict(self)

    def with_doubt(self, reason: str) -> Quality:
        """This verdict with one more doubt (evidence from outside `assess`): `improved` becomes
        `uncertain`, `degraded` stays; the reason goes first."""
        verdict = "uncertain" if self.verdict == "improved" else self.verdict
        kept = [r for r in self.reasons if not r.startswith(IMPROVED_REASON)]
        return dataclasses.replace(self, verdict=verdict, reasons=[reason, *kept])


def rms_point_to_plane(problem: FeatureProblem, T_world_scan: np.ndarray) -> float:
    """sqrt(plane cost / points) (m) of a problem at poses T_world_scan."""
    return float(np.sqrt(plane_cost(problem, T_world_scan) / max(problem.n_points, 1)))


def map_subsample(n_points_per_scan: Sequence[int], max_map_points: int) -> tuple[int, list[np.ndarray]]:
    """The map points of the map entropy: (stride s, per scan the sorted indices of its points kept).

    All points when they fit in `max_map_points`; else, with s the smallest integer that fits,
    ceil(N_k / s) points of scan k drawn without replacement by a generator seeded with k: the
    same points for any pose set, spread over every scan, and no aliasing with the scan pattern
    (a regular stride that divides the beam count would keep a few rings only, and a
    neighbourhood on a single ring is a line, far thinner than the map).
    """
    sizes = [int(n) for n in n_points_per_scan]
    stride = max(1, -(-sum(sizes) // max_map_points))
    if stride == 1:
        return 1, [np.arange(n) for n in sizes]
    return stride, [np.sort(np.random.default_rng(k).choice(n, -(-n // stride), replace=False))
                    for k, n in enumerate(sizes)]


def mean_map_entropy(scans_by_pose_set: dict[str, Sequence[np.ndarray]], T_by_pose_set: dict[str, np.ndarray],
                     n_points_per_scan: Sequence[int], radius_m: float, min_neighbours: int, max_map_points: int,
                     n_queries: int, query_seed: int = 0) -> dict[str, Any]:
    """The MME (nats) of each pose set on the same points (`map_subsample`) and query points (at
    most `n_queries` map points drawn without replacement by a generator seeded with `query_seed`).

    `scans_by_pose_set[name][k]`: scan k's (N_k, 3) points in its frame as that pose set sees
    them (deskewed by its trajectory; the same N_k = `n_points_per_scan[k]` points in the same
    order for every pose set; read one scan at a time, so only the subsampled map is held);
    `T_by_pose_set[name]`: (N, 4, 4) T_world_scan. A query point counts when it has at least
    `min_neighbours` neighbours under every pose set, so all are averaged over the same points.

    `surfaces` splits the query points by the normal of their neighbourhood (world z up):
    `upright` (walls, poles, trunks: the normal within 45 deg of horizontal under every pose set)
    fix the horizontal position and the heading, `level` (ground, roofs: within 45 deg of vertical
    under every pose set) the height, roll and pitch; a point classed differently under two pose
    sets is in neither. Per class: its query points, its MME per pose set and, for every pose set
    after the first, the standard error of the mean change from the first pose set (the standard
    deviation of the per-point changes over the square root of their count; None below two points):
    the spread of that mean over draws of the query points, the points and poses being fixed.
    """
    names = list(T_by_pose_set)
    stride, kept = map_subsample(n_points_per_scan, max_map_points)
    n_map = sum(len(k) for k in kept)
    queries = np.sort(np.random.default_rng(query_seed).choice(n_map, min(n_queries, n_map), replace=False))
    entropies, normal_z = {}, {}
    for name in names:
        scans, T = scans_by_pose_set[name], T_by_pose_set[name]
        world = np.concatenate([np.asarray(scans[k], dtype=np.float64)[index] @ T[k, :3, :3].T + T[k, :3, 3]
                                for k, index in enumerate(kept)])
        entropies[name], normal_z[name] = neighbourhood_fit(world, world[queries], radius_m, min_neighbours,
                                                            ENTROPY_MIN_SIGMA_M)
    valid = np.all([np.isfinite(h) for h in entropies.values()], axis=0)

    def summary(members: np.ndarray) -> dict[str, Any]:
        first = entropies[names[0]][members]
        change_se = {}
        for name in names[1:]:
            change = entropies[name][members] - first
            change_se[name] = float(change.std() / np.sqrt(len(change))) if len(change) >= 2 else None
        return {"n_query_points": int(members.sum()),
                "mme_nats": {name: float(h[members].mean()) if np.any(members) else None
                             for name, h in entropies.items()},
                "change_standard_error_nats": change_se}

    upright_z = np.cos(np.pi / 4.0)
    upright = valid & np.all([z < upright_z for z in normal_z.values()], axis=0)
    level = valid & np.all([z >= upright_z for z in normal_z.values()], axis=0)
    return {"radius_m": radius_m, "min_neighbours": min_neighbours, "n_map_points": int(n_map),
            "map_stride": stride, "n_query_points": int(valid.sum()),
            "mme_nats": {name: float(h[valid].mean()) if np.any(valid) else None for name, h in entropies.items()},
            "surfaces": {"upright": summary(upright), "level": summary(level)}}


def observation_information(problem: FeatureProblem, normals_world: np.ndarray, T_world_scan: np.ndarray) -> np.ndarray:
    """(O, 6, 6) information each observation's points give on its scan's pose against its plane
    held fixed: 2 sum J J^T with J = [p x n; n], p a point rotated to world axes about its scan's
    origin and n the plane's world normal (coordinates: rotation (rad) about the scan's origin, world
    axes; translation (m), world axes). From the clusters' moments, no points needed."""
    R = T_world_scan[problem.scan_index, :3, :3]
    C = problem.clusters
    second = R @ C[:, :3, :3] @ R.transpose(0, 2, 1)  # sum p p^T
    first = np.einsum("oij,oj->oi", R, C[:, :3, 3])  # sum p
    n = normals_world[problem.plane_index]
    K = skew(n)  # p x n = -K p
    info = np.empty((len(n), 6, 6))
    info[:, :3, :3] = 2.0 * K @ second @ K.transpose(0, 2, 1)
    cross_sum = -np.einsum("oij,oj->oi", K, first)
    info[:, :3, 3:] = 2.0 * cross_sum[:, :, None] * n[:, None, :]
    info[:, 3:, :3] = info[:, :3, 3:].transpose(0, 2, 1)
    info[:, 3:, 3:] = 2.0 * C[:, 3, 3, None, None] * n[:, :, None] * n[:, None, :]
    return info


def pair_tie_information(problem: FeatureProblem, T_world_scan: np.ndarray) -> np.ndarray:
    """(N-1, 6, 6) information the landmarks scans j and j+1 both observe give on their relative
    motion: per shared landmark, the `observation_information` of the observation with fewer points
    (the weaker side limits the tie), summed. Coordinates of scan j+1's motion: rotation about its
    origin and translation, world axes."""
    normals = world_plane_stats(problem, T_world_scan)[1]
    info = observation_information(problem, normals, T_world_scan)
    n_scans = problem.n_scans
    M = np.zeros((max(n_scans - 1, 0), 6, 6))
    if problem.n_observations == 0:
        return M
    keys = problem.plane_index.astype(np.int64) * n_scans + problem.scan_index
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    nxt = np.searchsorted(sorted_keys, keys + 1)
    nxt = np.minimum(nxt, len(keys) - 1)
    shared = (sorted_keys[nxt] == keys + 1) & (problem.scan_index < n_scans - 1)
    a = np.flatnonzero(shared)
    b = order[nxt[a]]
    weaker = np.where(problem.clusters[a, 3, 3] <= problem.clusters[b, 3, 3], a, b)
    np.add.at(M, problem.scan_index[a], info[weaker])
    return M


def pair_ties(tie_information: np.ndarray, odometry_weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per consecutive pair: the smallest ratio of the shared planes' information to the odometry
    factor's over directions of the relative motion (generalised eigenvalue of (tie, odometry)), and
    that direction (6,) in the pair's coordinates (rotation rad, translation m; unit norm).

    `odometry_weights` (N-1, 6): the factors' weights sigma_point^2 / sigma^2 (rotation x3,
    translation x3); the factor's information is twice them (isotropic per block, so the same in
    any axes). A break of the relative motion by k odometry sigmas along a direction of ratio r
    raises the shared planes' cost by r k^2 sigma_point^2: it is visible (one sigma_point^2 or more)
    when r >= 1 / k^2.
    """
    w = 1.0 / np.sqrt(2.0 * odometry_weights)  # O^(-1/2)
    whitened = tie_information * w[:, :, None] * w[:, None, :]
    lam, vec = np.linalg.eigh(whitened)
    direction = vec[:, :, 0] * w
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
    return np.maximum(lam[:, 0], 0.0), direction


def _pairs(indices: np.ndarray) -> list[list[int]]:
    return [[int(j), int(j) + 1] for j in indices]


def _list(pairs: list[list[int]], limit: int = 8) -> str:
    text = ", ".join(f"{a}-{b}" for a, b in pairs[:limit])
    return text + (" ..." if len(pairs) > limit else "")


def decided_by_planes(tie_information: np.ndarray, residuals: np.ndarray, odometry_weights: np.ndarray,
                      T_world_scan: np.ndarray) -> np.ndarray:
    """(N-1,) whether the shared planes carry more information than the odometry factor along the
    change the refinement made to each pair's relative motion (`OdometryFactors.residuals` at the
    refined poses: rotation in scan j+1's frame, translation in scan j's): then the planes decided
    that change, not the odometry."""
    R = T_world_scan[:, :3, :3]
    delta = np.hstack([np.einsum("nij,nj->ni", R[1:], residuals[:, :3]),
                       np.einsum("nij,nj->ni", R[:-1], residuals[:, 3:])])
    planes = np.einsum("ni,nij,nj->n", delta, tie_information, delta)
    odometry = 2.0 * np.einsum("ni,ni->n", odometry_weights, delta**2)
    return planes >= odometry


_SURFACE_WORDS = {
    "upright": "upright surfaces (walls, poles, trunks: they fix the horizontal position and the heading)",
    "level": "level surfaces (ground, roofs: they fix the height, roll and pitch)",
}


def blurrier_surfaces(surfaces: dict[str, Any], standard_errors: float, tolerance_nats: float) -> dict[str, str]:
    """The classes of surfaces whose MME rose from the initial to the refined poses by more than
    `tolerance_nats` and by more than `standard_errors` standard errors of the mean change, each with
    its reason in words."""
    reasons = {}
    for name, s in surfaces.items():
        mme, se = s["mme_nats"], s["change_standard_error_nats"].get("refined")
        if se is None or mme["initial"] is None or mme["refined"] is None:
            continue
        change = mme["refined"] - mme["initial"]
        if change > max(standard_errors * se, tolerance_nats):
            rise = change / se if se > 0 else np.inf
            reasons[name] = (f"on {_SURFACE_WORDS[name]} the mean map entropy is {mme['refined']:.4f} nats refined "
                             f"against {mme['initial']:.4f} initial ({s['n_query_points']} query points; the rise is "
                             f"{rise:.1f} standard errors): the refined map is blurrier there")
    return reasons


def assess(rms: dict[str, dict[str, float]], odometry_sigmas: np.ndarray | None, ties: np.ndarray | None,
           settled: bool, outlier_sigma: float, rms_tolerance: float, entropy: dict[str, Any] | None = None,
           entropy_tolerance_nats: float = 0.0, planes_decide: np.ndarray | None = None,
           tie_words: Sequence[str] | None = None, held: Sequence[dict[str, Any]] = (),
           entropy_standard_errors: float = 3.0, free_space: dict[str, Any] | None = None) -> Quality:
    """The verdict on refined poses against initial ones (`Quality`).

    `rms[association][pose_set]` (m) for associations `planes_at_initial_poses`,
    `planes_at_refined_poses` and pose sets `initial`, `refined`; `odometry_sigmas` (N-1, 2):
    the change of each pair's relative rotation and translation in odometry sigmas (None: no
    factors); `ties` (N-1,): `pair_ties` ratios (None: no factors), a pair is tied when a break of
    `outlier_sigma` odometry sigmas would be visible in its shared planes (ratio >= 1 /
    outlier_sigma^2), `tie_words` the weakest direction of each pair in words; `planes_decide`
    (N-1,): `decided_by_planes` (None: all False); `entropy`: `mean_map_entropy` of the pose sets
    `initial` and `refined` (None: not measured); `held`: `scan_degeneracy`'s `held_by_odometry`;
    `free_space`: `free_space_check` of the pose sets `initial` and `refined` (None: not measured).
    The rule of `degraded`, `uncertain` and `improved` is the module's.

    Doubts (any makes the verdict `uncertain`): not sharper by an RMS (except the initial
    association's when the map-wide evidence is all better: a note) or the MME, more free-space
    violations beyond their standard errors, a class of
    surfaces (`mean_map_entropy`'s `surfaces`: upright, level) whose MME rose by more than
    `entropy_tolerance_nats` and by more than `entropy_standard_errors` standard errors of its mean
    change (listed in `blurrier_surfaces`), pairs changed beyond `outlier_sigma` odometry sigmas
    where the planes did not decide the change, untied pairs, not settled. Notes (stated in
    `reasons`, never lowering the verdict): pairs the planes corrected beyond the odometry model,
    scans held by odometry in some direction.
    """
    reasons: list[str] = []
    notes: list[str] = []
    worse: list[str] = []
    blurrier: dict[str, str] = {}
    mme = None if entropy is None else entropy["mme_nats"]
    if mme is not None and (mme["initial"] is None or mme["refined"] is None):
        mme = None  # no query point had enough neighbours: not measured
    map_reasons: list[str] = []
    if mme is not None:
        if mme["refined"] > mme["initial"] + entropy_tolerance_nats:
            worse.append("mean map entropy")
        if not mme["refined"] < mme["initial"]:
            map_reasons.append(f"mean map entropy ({entropy['radius_m']:g} m radius) is {mme['refined']:.4f} nats "
                               f"refined against {mme['initial']:.4f} initial: the refined map is not sharper by this "
                               "measure")
        blurrier = blurrier_surfaces(entropy.get("surfaces", {}), entropy_standard_errors, entropy_tolerance_nats)
        map_reasons.extend(blurrier.values())
    if free_space is not None:
        fraction, se = free_space["violation_fraction"], free_space["change_standard_error"]["refined"] or 0.0
        rise = fraction["refined"] - fraction["initial"]
        if rise > FREE_SPACE_STANDARD_ERRORS * se:
            ghost = fraction["refined"] > FREE_SPACE_DEGRADED_FACTOR * fraction["initial"]
            if ghost:
                worse.append("free space")
            pairs = free_space["inconsistent_pairs"]["refined"]
            map_reasons.append(
                f"{100 * fraction['refined']:.2f} % of the points of overlapping scans lie in space another scan saw "
                f"through at the refined poses, against {100 * fraction['initial']:.2f} % at the initial poses "
                f"({free_space['n_pairs']} pairs; the rise is {rise / se if se > 0 else np.inf:.1f} standard errors"
                + (f"; most at pairs {_list(pairs)}" if pairs else "") + "): "
                + ("surfaces were moved into seen-empty space (ghost copies)" if ghost else
                   "the refined map contradicts its free space more"))
    map_wide_better = mme is not None and free_space is not None and not map_reasons
    outvoted = False
    for a, r in rms.items():
        if r["refined"] < r["initial"]:
            continue
        text = (f"RMS point-to-plane on the {a.replace('_', ' ')} is {r['refined']:.4f} m refined against "
                f"{r['initial']:.4f} m initial")
        if a == "planes_at_initial_poses" and map_wide_better:
            outvoted = True
            notes.append(text + ": outvoted by the map-wide evidence (the mean map entropy, both classes of surfaces "
                         "and the free space are no worse), the planes found at the initial poses carry their errors")
            continue
        reasons.append(text + ": the refined map is not sharper there")
        if r["refined"] > r["initial"] * (1.0 + rms_tolerance):
            worse.append(a)
    reasons.extend(map_reasons)
    disagree: list[list[int]] = []
    corrected: list[list[int]] = []
    worst = None
    if odometry_sigmas is not None and len(odometry_sigmas):
        beyond = odometry_sigmas.max(axis=1) > outlier_sigma
        decided = np.zeros(len(beyond), dtype=bool) if planes_decide is None else np.asarray(planes_decide, bool)
        disagree, corrected = _pairs(np.flatnonzero(beyond & ~decided)), _pairs(np.flatnonzero(beyond & decided))
        worst = float(odometry_sigmas.max())
        if disagree:
            reasons.append(f"{len(disagree)} consecutive pair(s) changed their relative motion by more than "
                           f"{outlier_sigma:g} odometry sigmas where their shared planes carry less information than "
                           f"the odometry (pairs {_list(disagree)}): the odometry or the refinement is wrong there")
        if corrected:
            notes.append(f"the planes corrected the odometry by more than {outlier_sigma:g} of its sigmas at "
                         f"{len(corrected)} consecutive pair(s) (pairs {_list(corrected)}; up to {worst:.1f} sigmas): "
                         "their shared planes carry more information than the odometry along the change")
    untied: list[list[int]] = []
    if ties is not None:
        weak = np.flatnonzero(ties < 1.0 / outlier_sigma**2)
        untied = _pairs(weak)
        if len(weak):
            words = "" if tie_words is None else "; weakest: " + ", ".join(
                f"{j}-{j + 1} {tie_words[j]}" for j in weak[:3])
            reasons.append(f"{len(weak)} consecutive pair(s) share too few planes to see a break of "
                           f"{outlier_sigma:g} odometry sigmas in their relative motion (pairs "
                           f"{_list(untied)}{words}): there the relative motion rests on the odometry alone, and a "
                           "break would go unseen")
    if held:
        directions = sorted({d for h in held for d in h["directions"]})
        notes.append(f"{len(held)} scan(s) are held by the odometry more than by the planes in some direction "
                     f"(scans {', '.join(str(h['scan']) for h in held[:10])}{' ...' if len(held) > 10 else ''}: "
                     f"{'; '.join(directions[:4])}): the planes check those directions but do not decide them")
    if not settled:
        reasons.append("the rounds did not settle: the last round still moved a pose more than the tolerance")
    if worse:
        verdict = "degraded"
    elif reasons:
        verdict = "uncertain"
    else:
        verdict = "improved"
        planes = "the refined poses" if outvoted else "the initial and at the refined poses"
        reasons.append(IMPROVED_REASON + f" on planes found at {planes}" +
                       (" and by mean map entropy" if mme is not None else "") +
                       (", no more of its points lie in space other scans saw empty" if free_space else "") +
                       ", every consecutive pair shares planes that would show a break, changes beyond the "
                       "odometry model are the planes' decision, and the rounds settled")
    return Quality(
        verdict=verdict, reasons=reasons + notes, rms_point_to_plane_m=rms, map_entropy=entropy, free_space=free_space,
        blurrier_surfaces=sorted(blurrier), odometry_outlier_sigma=outlier_sigma,
        pairs_beyond_odometry_sigma=disagree, pairs_corrected_by_planes=corrected,
        n_scans_beyond_odometry_sigma=len({j for pair in disagree for j in pair}),
        max_odometry_change_sigma=worst,
        min_pair_tie=float(ties.min()) if ties is not None and len(ties) else None,
        pairs_not_tied_by_planes=untied, settled=bool(settled))


def verdict_warning(quality: dict[str, Any] | None) -> str | None:
    """The end-of-run warning for a verdict other than `improved` (None when improved or absent)."""
    if not quality or quality["verdict"] == "improved":
        return None
    lines = [f"WARNING: quality verdict '{quality['verdict'].upper()}' - do not trust the refined poses blindly:"]
    lines += [f"  - {reason}" for reason in quality["reasons"]]
    lines.append("  (see 'quality' in the report; --strict turns this into exit code 1)")
    return "\n".join(lines)
