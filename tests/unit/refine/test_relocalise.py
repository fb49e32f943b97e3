"""Scans the planes lost at a wrong initial pose are found again along their weak direction."""

import numpy as np
import pytest

from pa_cli.adjust.odometry_factors import OdometryFactors, OdometryModel
from pa_cli.config import PaConfig
from pa_cli.core.geometry import transform_points
from pa_cli.io.trajectory import read_trajectory
from pa_cli.planes import kernels
from pa_cli.planes.associate import build_plane_problem
from pa_cli.refine.relocalise import refuted_moves, relocalise_lost_scans, shift_information, unconfirmed_moves
from pa_cli.simulate.sensor import SimOptions
from pa_cli.simulate.writer import simulate
from pa_cli.sources import open_source

N_SCANS = 8


def _corridor(rng):
    """A 40 m corridor along x (floor, two side walls) closed by an end wall at x = 30 m, seen from
    poses 1 m apart along its axis: only the end wall fixes a scan along x. (scans, T_true)."""
    n = 6000
    floor = np.column_stack([rng.uniform(-10, 30, n), rng.uniform(-3, 3, n), np.zeros(n)])
    left = np.column_stack([rng.uniform(-10, 30, n), np.full(n, 3.0), rng.uniform(0, 3, n)])
    right = np.column_stack([rng.uniform(-10, 30, n), np.full(n, -3.0), rng.uniform(0, 3, n)])
    end = np.column_stack([np.full(n, 30.0), rng.uniform(-3, 3, n), rng.uniform(0, 3, n)])
    world = np.vstack([floor, left, right, end])
    T_true = np.tile(np.eye(4), (N_SCANS, 1, 1))
    T_true[:, 0, 3] = np.arange(N_SCANS, dtype=float)
    T_true[:, 2, 3] = 1.5
    scans = []
    for T in T_true:
        p = world[rng.choice(len(world), 8000, replace=False)] + rng.normal(0, 0.005, (8000, 3))
        scans.append((p - T[:3, 3]) @ T[:3, :3])
    return scans, T_true


def _relocalise(scans, T):
    config = PaConfig()
    found = {}
    problem, _ = build_plane_problem(scans, T, config.planes_config(), landmarks_out=found)
    odometry = OdometryFactors(T, OdometryModel.from_config(config)).linearize(T).pose_blocks
    return relocalise_lost_scans(scans, T, found["landmarks"], found["kept"], problem, odometry,
                                 config.advanced.degeneracy.lever_arm_m, search_m=3.0, step_m=0.02,
                                 outlier_sigma=config.advanced.planes.outlier_sigma,
                                 sigma_floor_m=config.advanced.planes.outlier_sigma_floor_m,
                                 min_points_per_observation=config.advanced.planes.min_points_per_observation)


def test_a_scan_registered_short_is_moved_back_along_its_weak_direction():
    scans, T_true = _corridor(np.random.default_rng(3))
    T_bad = T_true.copy()
    T_bad[2, 0, 3] -= 0.7  # scan 2 registered 0.7 m short: its end-wall points miss the landmark
    T_out, moved = _relocalise(scans, T_bad)
    assert [m["scan"] for m in moved] == [2]
    assert moved[0]["direction"] == "translation along the direction of travel"
    assert moved[0]["information_after"] > max(moved[0]["information_before"], moved[0]["odometry_information"])
    assert abs(T_out[2, 0, 3] - T_true[2, 0, 3]) <= 0.02  # back within one search step
    np.testing.assert_array_equal(np.delete(T_out, 2, axis=0), np.delete(T_bad, 2, axis=0))


def test_a_few_stray_points_on_a_landmark_do_not_hold_a_lost_scan():
    """Scan 2 registered 0.7 m short, with a few stray points (fewer than an observation needs,
    say through a gap in the end wall) that land on the end wall at the wrong pose: the
    association drops them, so they hold nothing. Counted point by point they would give more
    information along x than the odometry, and the scan would never be searched; counted as
    the association counts observations, the scan is lost, searched and found."""
    scans, T_true = _corridor(np.random.default_rng(6))
    config = PaConfig()
    n_stray = config.advanced.planes.min_points_per_observation - 1
    rng = np.random.default_rng(7)
    stray_world = np.column_stack([np.full(n_stray, 30.7), rng.uniform(-1, 1, n_stray), rng.uniform(0.5, 2.5, n_stray)])
    scans[2] = np.vstack([scans[2], (stray_world - T_true[2, :3, 3]) @ T_true[2, :3, :3]])
    T_bad = T_true.copy()
    T_bad[2, 0, 3] -= 0.7  # the stray points now lie on the end wall (x = 30 m), its own wall points 0.7 m short
    found = {}
    problem, _ = build_plane_problem(scans, T_bad, config.planes_config(), landmarks_out=found)
    odometry = OdometryFactors(T_bad, OdometryModel.from_config(config)).linearize(T_bad).pose_blocks
    landmarks = found["landmarks"]
    along = np.zeros(landmarks.n_landmarks + 1)
    along[found["kept"]] = 2.0 * landmarks.normal_world[found["kept"], 0] ** 2
    world = transform_points(T_bad[2], scans[2])
    gates = (config.advanced.planes.outlier_sigma, config.advanced.planes.outlier_sigma_floor_m)
    point_by_point = shift_information(landmarks, world, np.array([1.0, 0.0, 0.0]), along, np.zeros(1), 0.02, gates)
    assert point_by_point[0] > odometry[2, 3, 3]  # the stray points alone, counted one by one, outweigh the odometry
    T_out, moved = _relocalise(scans, T_bad)
    assert [m["scan"] for m in moved] == [2]
    assert moved[0]["information_before"] < moved[0]["odometry_information"] < moved[0]["information_after"]
    assert abs(T_out[2, 0, 3] - T_true[2, 0, 3]) <= 0.02
    np.testing.assert_array_equal(np.delete(T_out, 2, axis=0), np.delete(T_bad, 2, axis=0))


def test_scans_at_their_true_poses_stay():
    scans, T_true = _corridor(np.random.default_rng(4))
    T_out, moved = _relocalise(scans, T_true)
    assert moved == []
    np.testing.assert_array_equal(T_out, T_true)


def test_a_scan_the_planes_hold_is_not_moved_to_a_shallow_maximum():
    """Scan 2 off by 1 cm along x keeps its end-wall points (inside the gate): the planes hold it,
    and no search moves it to another maximum."""
    scans, T_true = _corridor(np.random.default_rng(5))
    T_off = T_true.copy()
    T_off[2, 0, 3] += 0.01
    T_out, moved = _relocalise(scans, T_off)
    assert moved == []
    np.testing.assert_array_equal(T_out, T_off)


def _assigned(landmarks, world, gates, min_points):
    """`Landmarks.assign` of world points, the labels fewer than min_points points take set to -1."""
    labels = landmarks.assign(world, *gates)[0]
    n_on = np.bincount(labels[labels >= 0], minlength=landmarks.n_landmarks)
    return np.where((labels >= 0) & (n_on[labels] >= min_points), labels, -1)


def _reference_relocalise(points, T_world_scan, landmarks, kept_landmarks, problem, odometry_information,
                          lever_arm_m, search_m, step_m, outlier_sigma, sigma_floor_m, min_points):
    """Brute force: every shift scored by `Landmarks.assign` on the shifted points (numpy sum); at
    the current position a landmark counts only with at least min_points of the scan's points."""
    from pa_cli.core.geometry import transform_points
    from pa_cli.evaluation.degeneracy import describe, travel_frames
    from pa_cli.refine.relocalise import weak_translations

    weak = weak_translations(problem, T_world_scan, odometry_information, lever_arm_m)
    T_out = np.array(T_world_scan, dtype=np.float64, copy=True)
    in_problem = np.zeros(landmarks.n_landmarks + 1, dtype=bool)
    in_problem[np.asarray(kept_landmarks, dtype=np.int64)] = True
    normals = np.vstack([landmarks.normal_world, np.zeros((1, 3))])
    n_steps = int(np.floor(search_m / step_m))
    shifts_m = np.arange(-n_steps, n_steps + 1) * step_m
    by_size = np.argsort(np.abs(shifts_m), kind="stable")
    frames = travel_frames(T_world_scan)
    moved = []

    def information(world, direction, along, shift_m, fewest=1):
        labels = _assigned(landmarks, world + shift_m * direction, (outlier_sigma, sigma_floor_m), fewest)
        return float(along[labels].sum())

    for j, direction in weak.items():
        world = transform_points(T_out[j], np.asarray(points[j], dtype=np.float64))
        along = np.where(in_problem, 2.0 * (normals @ direction) ** 2, 0.0)
        odometry = float(direction @ odometry_information[j, 3:, 3:] @ direction)
        here = information(world, direction, along, 0.0, min_points)
        if not here < odometry:
            continue
        scores = np.array([information(world, direction, along, s) for s in shifts_m])
        scores[shifts_m == 0.0] = here
        best = by_size[np.argmax(scores[by_size])]
        if not odometry < scores[best]:
            continue
        T_out[j, :3, 3] += shifts_m[best] * direction
        moved.append({"scan": int(j), "shift_m": float(shifts_m[best]),
                      "direction": describe(np.r_[np.zeros(3), direction], frames[j]),
                      "information_before": float(here), "information_after": float(scores[best]),
                      "odometry_information": odometry})
    return T_out, moved


@pytest.fixture(scope="module")
def town_with_lost_scans(tmp_path_factory):
    """A town circuit whose poses are off along the track (smooth, as odometry drifts, and every
    ninth scan by a further 0.3 to 1.5 m): scans whose planes across the track are missed.
    (points, T, found, problem, odometry)."""
    out = tmp_path_factory.mktemp("reloc") / "town"
    simulate(SimOptions(scene="town", path="circuit", scans=120, step_m=1.0, beams=16, azimuth_steps=256,
                        seed=8), out)
    source = open_source(out / "scans")
    points = [source.points(k) for k in range(len(source))]
    T = read_trajectory(out / "gt_poses_kitti.txt").T_world_scan.copy()
    travel = np.gradient(T[:, :3, 3], axis=0)
    travel /= np.linalg.norm(travel, axis=1, keepdims=True)
    rng = np.random.default_rng(9)
    error_m = np.convolve(rng.normal(0, 0.6, len(T) + 20), np.ones(21) / np.sqrt(21), mode="valid")[:len(T)]
    error_m[::9] += rng.choice([-1.0, 1.0], len(error_m[::9])) * rng.uniform(0.3, 1.5, len(error_m[::9]))
    T[:, :3, 3] += error_m[:, None] * travel
    config = PaConfig()
    found: dict = {}
    problem, _ = build_plane_problem(points, T, config.planes_config(), landmarks_out=found)
    odometry = OdometryFactors(T, OdometryModel.from_config(config)).linearize(T).pose_blocks
    return points, T, found, problem, odometry


def test_pairwise_sum_equals_numpy_sum_bit_for_bit():
    rng = np.random.default_rng(11)
    for n in [*range(0, 300), 1000, 8191, 8192, 8193, 65537]:
        values = rng.random(n) * (rng.random(n) < 0.3)
        assert kernels._pairwise_sum(values, 0, n) == values.sum()


def test_shift_information_equals_assign_at_every_shift(town_with_lost_scans):
    """The kernel's information per shift is `along[labels].sum()` of `Landmarks.assign` on the
    shifted points (labels of fewer than min_points points dropped), bit for bit, for directions
    of any kind (brute force over all shifts)."""
    points, T, found, problem, _ = town_with_lost_scans
    config = PaConfig()
    landmarks = found["landmarks"]
    gates = (config.advanced.planes.outlier_sigma, config.advanced.planes.outlier_sigma_floor_m)
    rng = np.random.default_rng(12)
    shifts_m = np.arange(-75, 76) * 0.02
    n_nonzero = 0
    n_dropped = 0
    for j in (3, 40, 77):
        world = transform_points(T[j], np.asarray(points[j], dtype=np.float64))
        for direction in (rng.normal(size=3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])):
            direction = direction / np.linalg.norm(direction)
            along = np.r_[rng.uniform(0.0, 2.0, landmarks.n_landmarks), 0.0]
            along[:-1][rng.random(landmarks.n_landmarks) < 0.3] = 0.0
            every = None
            for min_points in (1, config.advanced.planes.min_points_per_observation):
                fast = shift_information(landmarks, world, direction, along, shifts_m, 0.02, gates, min_points)
                slow = np.array([along[_assigned(landmarks, world + s * direction, gates, min_points)].sum()
                                 for s in shifts_m])
                np.testing.assert_array_equal(fast, slow)
                n_nonzero += int((slow > 0).sum())
                if every is not None:
                    n_dropped += int((slow < every).sum())
                every = slow
    assert n_nonzero > 100
    assert n_dropped > 10  # the minimum count decides some shifts


@pytest.fixture(scope="module")
def relocalise_arguments(town_with_lost_scans):
    points, T, found, problem, odometry = town_with_lost_scans
    config = PaConfig()
    return (points, T, found["landmarks"], found["kept"], problem, odometry, config.advanced.degeneracy.lever_arm_m,
            3.0, 0.02, config.advanced.planes.outlier_sigma, config.advanced.planes.outlier_sigma_floor_m,
            config.advanced.planes.min_points_per_observation)


@pytest.fixture(scope="module")
def brute_force(relocalise_arguments):
    return _reference_relocalise(*relocalise_arguments)


@pytest.mark.slow  # the brute-force reference searches every shift of every scan in Python (about 20 s)
@pytest.mark.parametrize("threads", [1, 2])
def test_relocalisation_equals_the_brute_force_search(relocalise_arguments, brute_force, threads):
    T_fast, moved_fast = relocalise_lost_scans(*relocalise_arguments, threads=threads)
    T_slow, moved_slow = brute_force
    assert len(moved_slow) >= 3
    assert moved_fast == moved_slow
    np.testing.assert_array_equal(T_fast, T_slow)


def _reassociated(scans, T):
    """The plane problem associated afresh at poses T (default planes config)."""
    return build_plane_problem(scans, T, PaConfig().planes_config())[0]


def _along_x(T, j):
    """The odometry factors' information along x for scan j at poses T (the record's figure)."""
    return float(OdometryFactors(T, OdometryModel.from_config(PaConfig())).linearize(T).pose_blocks[j, 3, 3])


def _confirmation(scans, T_before, T_after, records):
    return unconfirmed_moves(_reassociated(scans, T_before), T_before, _reassociated(scans, T_after), T_after,
                             records)


def test_a_move_back_to_the_true_pose_is_confirmed_by_the_new_association():
    scans, T_true = _corridor(np.random.default_rng(3))
    T_bad = T_true.copy()
    T_bad[2, 0, 3] -= 0.7
    T_out, moved = _relocalise(scans, T_bad)
    assert [m["scan"] for m in moved] == [2]
    assert _confirmation(scans, T_bad, T_out, moved) == []
    assert moved[0]["held_after"] > moved[0]["odometry_information"] + moved[0]["held_before"]


@pytest.mark.parametrize("shift_m", [0.7, -0.4])
def test_a_move_away_from_the_true_pose_is_not_confirmed(shift_m):
    """Scan 2 at its true pose, moved along x: its end-wall points leave the wall's gate, and the
    association at the moved poses holds it along x less than the odometry did, so the move is
    named; the reverse move, from the wrong pose back to the truth, is confirmed."""
    scans, T_true = _corridor(np.random.default_rng(9))
    T_moved = T_true.copy()
    T_moved[2, 0, 3] += shift_m
    record = [{"scan": 2, "shift_m": shift_m, "odometry_information": _along_x(T_true, 2)}]
    assert _confirmation(scans, T_true, T_moved, record) == [2]
    assert record[0]["held_after"] < record[0]["odometry_information"] < record[0]["held_before"]
    assert _confirmation(scans, T_moved, T_true, record) == []


def _panels(rng):
    """A corridor with panels across it every 2 m (railing posts, a facade's bays) and no end wall, seen from
    poses 1 m apart along it: (scans, T_true)."""
    n = 6000
    floor = np.column_stack([rng.uniform(-10, 40, n), rng.uniform(-3, 3, n), np.zeros(n)])
    left = np.column_stack([rng.uniform(-10, 40, n), np.full(n, 3.0), rng.uniform(0, 3, n)])
    right = np.column_stack([rng.uniform(-10, 40, n), np.full(n, -3.0), rng.uniform(0, 3, n)])
    panels = [np.column_stack([np.full(800, x), rng.uniform(-1.0, -0.5, 800), rng.uniform(0.5, 1.5, 800)])
              for x in np.arange(8.0, 34.0, 2.0)]
    world = np.vstack([floor, left, right, *panels])
    T_true = np.tile(np.eye(4), (N_SCANS, 1, 1))
    T_true[:, 0, 3] = np.arange(N_SCANS, dtype=float)
    T_true[:, 2, 3] = 1.5
    scans = [(world + rng.normal(0, 0.005, world.shape) - T[:3, 3]) @ T[:3, :3] for T in T_true]
    return scans, T_true


def test_a_move_one_period_along_a_repeated_structure_is_not_confirmed():
    """Scan 2 of `_panels` moved by one period lands its panel points on the neighbouring panels, and the
    planes found there hold it along x more firmly than the odometry does, but no more firmly than it was
    held at its true pose (by the same panels and the odometry): not confirmed."""
    scans, T_true = _panels(np.random.default_rng(11))
    T_moved = T_true.copy()
    T_moved[2, 0, 3] += 2.0
    record = [{"scan": 2, "shift_m": 2.0, "odometry_information": _along_x(T_true, 2)}]
    assert _confirmation(scans, T_true, T_moved, record) == [2]
    assert record[0]["held_after"] > record[0]["odometry_information"]  # held there, but not more than before


def _refuted(scans, T_before, T_moved, scans_moved):
    config = PaConfig().advanced.hold
    records = [{"scan": j} for j in scans_moved]
    return refuted_moves(scans, T_before, T_moved, records, config.registration_voxel_m,
                         config.registration_max_correspondence_m), records


@pytest.mark.parametrize("moved", [[2], [2, 3]])
def test_a_move_one_period_along_a_repeated_structure_is_refuted_by_the_neighbouring_scans(moved):
    """Scans of `_panels` moved by one period (alone, or two together): their panels line up with their
    neighbours' again, but the rest of their points do not (the corridor's ends move with them), so the pairs
    from the scan before them to the scan after fit worse and the moves are refuted; the moves back are not."""
    scans, T_true = _panels(np.random.default_rng(11))
    T_moved = T_true.copy()
    T_moved[moved, 0, 3] += 2.0
    refuted, records = _refuted(scans, T_true, T_moved, moved)
    assert refuted == moved
    assert all(r["pair_cost_after_m2"] > r["pair_cost_before_m2"] for r in records)
    assert _refuted(scans, T_moved, T_true, moved)[0] == []


def test_a_move_back_to_the_true_pose_fits_the_neighbouring_scans_and_stands():
    """Scan 2 of the corridor 0.7 m short (its end-wall points off the neighbours' end wall): the move to
    its true pose fits scans 1 and 3 better and stands, and scans moved apart (2 and 5) are judged each on
    its own pairs: scan 5 moved further from the truth is refuted, scan 2 moved to it stands."""
    scans, T_true = _corridor(np.random.default_rng(3))
    T_bad = T_true.copy()
    T_bad[[2, 5], 0, 3] -= 0.7
    refuted, records = _refuted(scans, T_bad, T_true, [2, 5])
    assert refuted == []
    assert all(r["pair_cost_after_m2"] < r["pair_cost_before_m2"] for r in records)
    T_mixed = T_true.copy()
    T_mixed[5, 0, 3] -= 1.4  # further from the truth
    assert _refuted(scans, T_bad, T_mixed, [2, 5])[0] == [5]


@pytest.mark.parametrize("shift_m", [0.001, 0.005])
def test_a_move_within_the_pairs_noise_is_not_refuted(shift_m):
    """Scan 2 of the corridor moved by millimetres along x from its true pose: the pairs' points fit worse by
    less than REFUTE_STANDARD_ERRORS standard errors of their change (5 mm point noise), so the planes decide."""
    scans, T_true = _corridor(np.random.default_rng(3))
    T_moved = T_true.copy()
    T_moved[2, 0, 3] += shift_m
    refuted, records = _refuted(scans, T_true, T_moved, [2])
    assert refuted == []
    assert abs(records[0]["pair_cost_change_standard_errors"]) < 3.0
