"""The free-space check: against a brute-force ray test, against the scene's geometry, and in the
verdict (ghost copies of a room are caught while the map entropy improves; a correct refinement is not)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pa_cli.evaluation.free_space import (
    FREE_SPACE_SIGMAS,
    RangeImage,
    free_space_check,
    near_pairs,
    pixel_size_rad,
    scan_pairs,
)
from pa_cli.evaluation.quality import assess, mean_map_entropy

ROOM = (np.array([-4.0, -3.0, -1.2]), np.array([5.0, 3.0, 1.8]))  # walls, floor, ceiling (m)
PILLAR = (np.array([1.0, 0.5, -1.2]), np.array([1.6, 1.1, 1.8]))  # a pillar that breaks the room's symmetry
BEAMS_DEG = np.linspace(-15.0, 15.0, 16)
AZIMUTH_STEPS = 360
NOISE_M = 0.005
DEPTH_M = 0.3  # the map entropy's radius
GOOD_RMS = {"planes_at_initial_poses": {"initial": 0.03, "refined": 0.01},
            "planes_at_refined_poses": {"initial": 0.05, "refined": 0.01}}
ARGS = {"outlier_sigma": 5.0, "rms_tolerance": 0.01, "entropy_tolerance_nats": 0.03}


def _pose(x, y, yaw_deg):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    T[:3, 3] = [x, y, 0.0]
    return T


def _scan(T_world_scan, rng):
    """The room and pillar ray-cast from the sensor at T_world_scan: (N, 3) points in the scan frame."""
    el, az = np.meshgrid(np.deg2rad(BEAMS_DEG), np.linspace(-np.pi, np.pi, AZIMUTH_STEPS, endpoint=False))
    d_scan = np.column_stack([(np.cos(el) * np.cos(az)).ravel(), (np.cos(el) * np.sin(az)).ravel(),
                              np.sin(el).ravel()])
    d = d_scan @ T_world_scan[:3, :3].T
    o = T_world_scan[:3, 3]
    with np.errstate(divide="ignore"):
        inv = 1.0 / d
    t_exit = np.min(np.maximum((ROOM[0] - o) * inv, (ROOM[1] - o) * inv), axis=1)  # leaving the room
    t0, t1 = (PILLAR[0] - o) * inv, (PILLAR[1] - o) * inv
    near, far = np.max(np.minimum(t0, t1), axis=1), np.min(np.maximum(t0, t1), axis=1)
    t = np.where((near <= far) & (near > 0), np.minimum(near, t_exit), t_exit)
    t = t + rng.normal(0.0, NOISE_M, len(t))
    return d_scan * t[:, None]


def _sequence(n_scans=10, seed=0):
    rng = np.random.default_rng(seed)
    T = np.array([_pose(-3.0 + 0.7 * k, -1.5 + 0.25 * k, 10.0 * k) for k in range(n_scans)])
    return T, [_scan(T[k], rng) for k in range(n_scans)]


def _brute_force(image_points, projected, noise_m, depth_m, pixel_rad):
    """Violations by the definition, one point at a time: the returns of the image scan whose ray
    falls in the point's pixel give the nearest range and their spread, those of the eight pixels
    around it (azimuth wrapping) the range change across it; a point is a violation when it lies
    in front of the nearest return by more than the noise margin plus that change plus depth_m."""
    def pixel(p):
        el = np.arctan2(p[2], np.hypot(p[0], p[1]))
        az = np.arctan2(p[1], p[0])
        return int((el + np.pi / 2) // pixel_rad[0]), int((az + np.pi) // pixel_rad[1])

    n_columns = int(np.ceil(2 * np.pi / pixel_rad[1]))
    returns = {}
    for p in image_points:
        returns.setdefault(pixel(p), []).append(np.linalg.norm(p))
    out = []
    for p in projected:
        row, col = pixel(p)
        here = returns.get((row, col % n_columns))
        if not here:
            out.append(False)
            continue
        nearest = min(here)
        changes = [max(here) - nearest]
        n_neighbours = 0
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                other = returns.get((row + dr, (col + dc) % n_columns))
                if (dr or dc) and other:
                    changes.append(abs(min(other) - nearest))
                    n_neighbours += 1
        margin = FREE_SPACE_SIGMAS * np.sqrt(2) * noise_m + max(changes) + depth_m
        out.append(n_neighbours > 0 and np.linalg.norm(p) < nearest - margin)
    return np.array(out)


def test_range_image_matches_a_brute_force_ray_test():
    T, scans = _sequence(4)
    pixel_rad = pixel_size_rad(scans)
    rng = np.random.default_rng(1)
    image = RangeImage.of(scans[0], pixel_rad)
    T_0_2 = np.linalg.inv(T[0]) @ T[2]
    projected = np.vstack([scans[2] @ T_0_2[:3, :3].T + T_0_2[:3, 3],
                           rng.uniform(-6.0, 6.0, (3000, 3)),  # anywhere, also behind the walls
                           rng.normal(0.0, 1.0, (200, 3)) + [-6.0, 0.0, 0.0]])  # around azimuth pi (the seam)
    found = image.violations(projected, NOISE_M, DEPTH_M)
    expected = _brute_force(scans[0], projected, NOISE_M, DEPTH_M, pixel_rad)
    assert found.sum() > 100  # the random points in the room do violate
    np.testing.assert_array_equal(found, expected)


def test_pixel_size_is_one_beam_by_one_azimuth_step():
    _, scans = _sequence(3)
    elevation, azimuth = np.rad2deg(pixel_size_rad(scans))
    assert elevation == pytest.approx(2.0, rel=0.01)  # 16 beams over 30 deg
    assert azimuth == pytest.approx(360.0 / AZIMUTH_STEPS, rel=0.1)


def test_points_in_seen_empty_space_violate_and_surfaces_do_not():
    T, scans = _sequence(3)
    image = RangeImage.of(scans[0], pixel_size_rad(scans))
    T_0_1 = np.linalg.inv(T[0]) @ T[1]
    surfaces = scans[1] @ T_0_1[:3, :3].T + T_0_1[:3, 3]  # the same room seen from scan 1: on scan 0's surfaces
    assert image.violations(surfaces, NOISE_M, 0.0).mean() < 0.002
    # scan 0's own returns pulled towards the sensor: in the space its rays crossed
    hits = scans[0][np.linalg.norm(scans[0], axis=1) > 1.5]
    range_m = np.linalg.norm(hits, axis=1)
    tested = np.isfinite(image.footprint_m.ravel()[image.nearest_m.ravel() < np.inf]).mean()
    assert image.violations(hits * (1.0 - 0.6 / range_m)[:, None], NOISE_M, DEPTH_M).mean() > 0.8 * tested
    # by less than depth_m: a blur, the map entropy's to judge
    assert image.violations(hits * (1.0 - 0.2 / range_m)[:, None], NOISE_M, DEPTH_M).mean() < 0.01
    assert not image.violations(hits * (1.0 + 0.6 / range_m)[:, None], NOISE_M, DEPTH_M).any()  # behind


def test_pairs_are_consecutive_and_near_under_any_pose_set():
    T = np.array([_pose(float(k), 0.0, 0.0) for k in range(6)])
    T_far = T.copy()
    T_far[5, :3, 3] = [0.5, 0.0, 0.0]  # scan 5 brought back next to scan 0
    pairs = scan_pairs({"a": T, "b": T_far}, near_m=1.2)  # scans 1 m apart: only consecutive ones are near
    assert pairs.tolist() == [[0, 1], [0, 5], [1, 2], [1, 5], [2, 3], [3, 4], [4, 5]]
    assert len(scan_pairs({"a": T}, near_m=10.0, max_pairs=7)) == 7


def test_near_pairs_are_those_of_a_brute_force_over_all_pairs():
    rng = np.random.default_rng(5)
    n = 300
    T_a = np.tile(np.eye(4), (n, 1, 1))
    T_a[:, :3, 3] = np.cumsum(rng.normal(0.0, 1.0, (n, 3)), axis=0)  # a wandering path that crosses itself
    T_b = T_a.copy()
    T_b[:, :3, 3] += rng.normal(0.0, 0.5, (n, 3))
    T_b[7, :3, 3] = T_b[200, :3, 3] + [2.0, 0.0, 0.0]  # a pair exactly at the distance: not near (strict)
    poses = {"a": T_a, "b": T_b}
    a, b = np.triu_indices(n, k=2)
    near = np.zeros(len(a), dtype=bool)
    for T in poses.values():
        near |= np.linalg.norm(T[a, :3, 3] - T[b, :3, 3], axis=1) < 2.0
    expected = np.column_stack([a[near], b[near]])
    found = near_pairs(poses, 2.0)
    assert len(expected) > 50
    np.testing.assert_array_equal(found, expected)
    assert [7, 200] not in found.tolist()


def _ghosted(T):
    """The second half of the poses turned 40 deg about the room's centre: two sharp copies of the room."""
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 40.0, degrees=True).as_matrix()
    out = T.copy()
    out[len(T) // 2:] = turn @ T[len(T) // 2:]
    return out


def _blurred(T, seed=2):
    rng = np.random.default_rng(seed)
    out = T.copy()
    for k in range(len(T)):
        out[k, :3, :3] = Rotation.from_rotvec(rng.normal(0.0, np.deg2rad(0.2), 3)).as_matrix() @ T[k, :3, :3]
        out[k, :3, 3] += rng.normal(0.0, 0.01, 3)
    return out


def _evidence(scans, T_initial, T_refined):
    pose_sets = {"initial": T_initial, "refined": T_refined}
    sets = {name: scans for name in pose_sets}
    entropy = mean_map_entropy(sets, pose_sets, [len(s) for s in scans], 0.3, 10, 1_000_000, 5000)
    return entropy, free_space_check(sets, pose_sets, NOISE_M, DEPTH_M)


def test_ghost_copies_light_up_the_free_space_while_the_map_entropy_improves():
    T, scans = _sequence()
    entropy, free = _evidence(scans, _blurred(T), _ghosted(T))
    mme = entropy["mme_nats"]
    assert mme["refined"] < mme["initial"] - 0.1  # two sharp copies: sharper than the blurred start
    fraction, se = free["violation_fraction"], free["change_standard_error"]["refined"]
    assert fraction["refined"] > 3.0 * fraction["initial"] and fraction["refined"] - fraction["initial"] > 3.0 * se
    assert free["inconsistent_pairs"]["refined"]
    assert all((a < 5) != (b < 5) for a, b in free["inconsistent_pairs"]["refined"])  # pairs across the copies
    q = assess(GOOD_RMS, None, None, True, **ARGS, entropy=entropy, free_space=free)
    assert q.verdict == "degraded" and any("ghost copies" in r for r in q.reasons)
    assert assess(GOOD_RMS, None, None, True, **ARGS, entropy=entropy).verdict == "improved"  # blind without it


def test_a_correct_refinement_is_not_flagged():
    T, scans = _sequence()
    entropy, free = _evidence(scans, _blurred(T), T)
    fraction, se = free["violation_fraction"], free["change_standard_error"]["refined"]
    assert fraction["refined"] <= fraction["initial"] + 3.0 * se
    assert free["inconsistent_pairs"]["refined"] == []
    q = assess(GOOD_RMS, None, None, True, **ARGS, entropy=entropy, free_space=free)
    assert q.verdict == "improved" and q.free_space is free


def _free(initial, refined, se=0.001):
    return {"n_pairs": 50, "violation_fraction": {"initial": initial, "refined": refined},
            "change_standard_error": {"refined": se}, "inconsistent_pairs": {"refined": []}}


def _entropy(initial, refined, upright_rise=-0.1):
    surfaces = {"upright": {"n_query_points": 400, "mme_nats": {"initial": -2.7, "refined": -2.7 + upright_rise},
                            "change_standard_error_nats": {"refined": 0.01}}}
    return {"radius_m": 0.3, "mme_nats": {"initial": initial, "refined": refined}, "surfaces": surfaces}


def test_the_rms_on_the_initial_planes_is_outvoted_by_the_map_wide_evidence():
    rms = {a: dict(r) for a, r in GOOD_RMS.items()}
    rms["planes_at_initial_poses"] = {"initial": 0.0247, "refined": 0.0251}  # +1.6 %
    q = assess(rms, None, None, True, **ARGS, entropy=_entropy(-2.0, -2.2), free_space=_free(0.010, 0.009))
    assert q.verdict == "improved" and any("outvoted" in r for r in q.reasons)
    # without the free space, or with one piece of map-wide evidence worse, the RMS rise decides again
    assert assess(rms, None, None, True, **ARGS, entropy=_entropy(-2.0, -2.2)).verdict == "degraded"
    assert assess(rms, None, None, True, **ARGS, entropy=_entropy(-2.0, -2.2, upright_rise=0.1),
                  free_space=_free(0.010, 0.009)).verdict == "degraded"
    assert assess(rms, None, None, True, **ARGS, entropy=_entropy(-2.0, -2.2),
                  free_space=_free(0.010, 0.015)).verdict == "degraded"
    # the RMS on the planes found at the refined poses is never outvoted
    rms = {a: dict(r) for a, r in GOOD_RMS.items()}
    rms["planes_at_refined_poses"]["refined"] = 0.06
    assert assess(rms, None, None, True, **ARGS, entropy=_entropy(-2.0, -2.2),
                  free_space=_free(0.010, 0.009)).verdict == "degraded"


def test_more_free_space_violations_are_a_doubt_and_doubled_ones_degrade():
    def verdict(initial, refined):
        return assess(GOOD_RMS, None, None, True, **ARGS, entropy=_entropy(-2.0, -2.2),
                      free_space=_free(initial, refined)).verdict

    assert verdict(0.010, 0.0125) == "improved"  # within 3 standard errors
    assert verdict(0.010, 0.015) == "uncertain"  # beyond them, below twice
    assert verdict(0.010, 0.025) == "degraded"


def test_pose_sets_sharing_one_sequence_score_as_with_a_copy_each():
    """One sequence object for every pose set (its projected points and range images made once) gives
    the result of a copy of it per pose set."""
    T, scans = _sequence()
    pose_sets = {"initial": _blurred(T), "refined": _ghosted(T)}
    shared = free_space_check(dict.fromkeys(pose_sets, scans), pose_sets, NOISE_M, DEPTH_M)
    copies = {name: [points.copy() for points in scans] for name in pose_sets}
    assert shared == free_space_check(copies, pose_sets, NOISE_M, DEPTH_M)
