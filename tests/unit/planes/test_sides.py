"""The sensor's side of a plane: the two faces of a thin wall are two landmarks (pa_cli.planes.sides)."""

from __future__ import annotations

import numpy as np
import pytest

from pa_cli.adjust import solve
from pa_cli.config import PlanesConfig, SolverConfig
from pa_cli.core.geometry import exp_so3
from pa_cli.planes.associate import build_plane_problem, world_plane_stats
from pa_cli.planes.sides import observation_sides, split_two_sided

WALL_Y_M = 0.2  # face A (room A, y < WALL_Y_M); off the voxel grid's planes
THICKNESS_M = 0.06  # face B at WALL_Y_M + THICKNESS_M (room B): both faces fit in one planar voxel
CEILING_SLOPE = 0.4  # a sloped ceiling over both rooms ties their y through z
ROOM_M = 6.0


def _rect(rng, n, fixed_axis, fixed_value, lo, hi):
    p = lo + rng.random((n, 3)) * (np.asarray(hi) - np.asarray(lo))
    p[:, fixed_axis] = fixed_value
    return p


def _visible_points(rng: np.random.Generator, in_room_b: bool, n: int = 600) -> np.ndarray:
    """World points a sensor in room A (or B) sees: floor, sloped ceiling, side walls, the end wall and
    its own face of the thin wall (an opaque wall hides the other face)."""
    face_y = WALL_Y_M + THICKNESS_M if in_room_b else WALL_Y_M
    y0, y1 = (face_y, face_y + ROOM_M) if in_room_b else (face_y - ROOM_M, face_y)
    end_y = y1 if in_room_b else y0
    parts = [_rect(rng, 2 * n, 2, 0.0, (0, y0, 0), (10, y1, 0)),
             _rect(rng, n, 0, 0.0, (0, y0, 0), (0, y1, 3)), _rect(rng, n, 0, 10.0, (0, y0, 0), (10, y1, 3)),
             _rect(rng, n, 1, end_y, (0, 0, 0), (10, 0, 3)), _rect(rng, 2 * n, 1, face_y, (0, 0, 0), (10, 0, 3))]
    ceiling = _rect(rng, 2 * n, 2, 0.0, (0, y0, 0), (10, y1, 0))
    ceiling[:, 2] = 3.0 + CEILING_SLOPE * ceiling[:, 1]
    return np.vstack(parts + [ceiling])


def _poses(rooms: tuple[bool, ...]) -> np.ndarray:
    T = np.tile(np.eye(4), (0, 1, 1))
    rows = []
    for b in rooms:
        k = len(rows)
        M = np.eye(4)
        M[:3, :3] = exp_so3(np.array([[0.0, 0.0, 0.2 * k]]))[0]
        y = WALL_Y_M + THICKNESS_M + 2.5 + 0.1 * k if b else WALL_Y_M - 2.5 - 0.1 * k
        M[:3, 3] = [2.5 + 0.6 * k, y, 1.2]
        rows.append(M)
    return np.stack(rows) if rows else T


def _scans(T: np.ndarray, rooms: tuple[bool, ...], seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    scans = []
    for M, b in zip(T, rooms, strict=True):
        world = _visible_points(rng, b)
        scan = (world - M[:3, 3]) @ M[:3, :3]
        scans.append(scan + rng.normal(scale=0.003, size=scan.shape))
    return scans


def _wall_planes(problem, T) -> list[tuple[float, set[bool]]]:
    """(y offset, rooms observing) of the problem planes with a normal along y near the thin wall."""
    _, normal, _ = world_plane_stats(problem, T)
    out = []
    for p in np.flatnonzero(np.abs(normal[:, 1]) > 0.99):
        obs = np.flatnonzero(problem.plane_index == p)
        C = sum(T[j] @ problem.clusters[o] @ T[j].T for o, j in zip(obs, problem.scan_index[obs], strict=True))
        y = C[1, 3] / C[3, 3]
        if abs(y - WALL_Y_M) < 0.5:
            out.append((float(y), {bool(T[j][1, 3] > WALL_Y_M) for j in problem.scan_index[obs]}))
    return out


ROOMS = (False, True) * 4
PLANES = PlanesConfig(voxel_size_m=0.5)


def test_thin_wall_faces_are_two_landmarks_at_the_truth():
    T = _poses(ROOMS)
    problem, diag = build_plane_problem(_scans(T, ROOMS, seed=3), T, PLANES)
    assert diag["n_landmarks_two_sided"] >= 1  # detection merged the faces: the split had work to do
    walls = _wall_planes(problem, T)
    assert {frozenset(rooms) for _, rooms in walls} == {frozenset({False}), frozenset({True})}
    for y, rooms in walls:  # each landmark observed from one room only, on that room's face
        face_y = WALL_Y_M + THICKNESS_M if rooms == {True} else WALL_Y_M
        assert y == pytest.approx(face_y, abs=0.005)


def test_thin_wall_does_not_pull_the_poses():
    T_true = _poses(ROOMS)
    scans = _scans(T_true, ROOMS, seed=4)
    rng = np.random.default_rng(5)
    T0 = T_true.copy()
    for M in T0[1:]:  # pose 0 is the gauge
        M[:3, :3] = exp_so3(rng.normal(scale=np.deg2rad(0.3), size=(1, 3)))[0] @ M[:3, :3]
        M[:3, 3] += rng.normal(scale=0.02, size=3)
    problem, diag = build_plane_problem(scans, T0, PLANES)
    assert diag["n_landmarks_two_sided"] >= 1
    result = solve(problem, T0, SolverConfig())
    error_m = np.linalg.norm(result.T_world_scan[:, :3, 3] - T_true[:, :3, 3], axis=1)
    # a merged wall would pull the rooms THICKNESS_M together (the faces made coplanar)
    assert error_m.max() < 0.1 * THICKNESS_M


def test_wall_seen_from_one_side_is_unchanged():
    rooms = (False,) * 6
    T = _poses(rooms)
    found: dict = {}
    problem, diag = build_plane_problem(_scans(T, rooms, seed=6), T, PLANES, landmarks_out=found)
    assert "n_landmarks_two_sided" not in diag
    labels = [lab.copy() for lab in found["landmark_of_point"]]
    n_landmarks = found["landmarks"].n_landmarks
    # every observation of the problem from one side: splitting finds nothing and changes nothing
    lm = np.asarray(found["kept"])[problem.plane_index]
    assert split_two_sided(lm, problem.scan_index, problem.clusters, problem.clusters, T, found["landmarks"],
                           PLANES.side_grazing_angle_deg, found["landmark_of_point"]) is None
    assert found["landmarks"].n_landmarks == n_landmarks
    for a, b in zip(labels, found["landmark_of_point"], strict=True):
        np.testing.assert_array_equal(a, b)
    assert {frozenset(rooms) for _, rooms in _wall_planes(problem, T)} == {frozenset({False})}


def _cluster(points_scan: np.ndarray) -> np.ndarray:
    h = np.hstack([points_scan, np.ones((len(points_scan), 1))])
    return h.T @ h


@pytest.mark.parametrize("angle_deg,side", [(2.0, 0), (4.9, 0), (5.1, -1), (30.0, -1), (90.0, -1)])
def test_side_and_grazing_by_the_angle_of_the_mean_ray(angle_deg, side):
    # points around (d cos a, d sin a, 0) on the plane through them with normal +y; the sensor at
    # the origin sees them from -y at angle a to the plane
    a = np.deg2rad(angle_deg)
    centre = 20.0 * np.array([np.cos(a), np.sin(a), 0.0])
    rng = np.random.default_rng(0)
    pts = centre + np.column_stack([rng.normal(size=50), np.zeros(50), rng.normal(size=50)])
    normal = np.array([[0.0, 1.0, 0.0]])
    got = observation_sides(normal, _cluster(pts)[None], np.eye(3)[None], np.deg2rad(5.0))
    assert got.tolist() == [side]
    # the sign depends on the rotation, not on the translation: flip the scan by 180 deg about x
    R = exp_so3(np.array([[np.pi, 0.0, 0.0]]))
    pts_flipped = pts @ R[0]  # the same world points seen by a sensor rotated by R
    assert observation_sides(normal, _cluster(pts_flipped)[None], R, np.deg2rad(5.0)).tolist() == [side]


def test_grazing_observations_of_a_two_sided_landmark_are_dropped():
    rooms = ROOMS
    T = _poses(rooms)
    scans = _scans(T, rooms, seed=7)
    found: dict = {}
    build_plane_problem(scans, T, PLANES, landmarks_out=found)
    # a sensor in the wall's plane (angle 0 to it) sees the face edge-on: no side
    grid_x, grid_z = np.meshgrid(np.linspace(1, 9, 8), np.linspace(0.2, 2.8, 5))
    pts = np.column_stack([grid_x.ravel(), np.full(40, WALL_Y_M), grid_z.ravel()])
    M = np.eye(4)
    M[:3, 3] = [-5.0, WALL_Y_M, 1.5]
    normal = np.array([[0.0, 1.0, 0.0]])
    assert observation_sides(normal, _cluster(pts - M[:3, 3])[None], M[None, :3, :3], np.deg2rad(5.0)).tolist() == [0]
    landmarks = found["landmarks"]
    n_before = landmarks.n_landmarks
    lm = np.flatnonzero(np.abs(landmarks.normal_world[:, 1]) > 0.99)[0]
    face_b = pts + [0, THICKNESS_M, 0]
    clusters = np.stack([_cluster(pts - T[0, :3, 3]), _cluster(face_b - T[1, :3, 3]), _cluster(pts - M[:3, 3]),
                         _cluster(pts - T[2, :3, 3]), _cluster(face_b - T[3, :3, 3])])
    Ts = np.stack([_translation(T[0]), _translation(T[1]), M, _translation(T[2]), _translation(T[3])])
    # observations from one side and a grazing one: nothing changes
    assert split_two_sided(np.full(3, lm), np.arange(3), clusters[[0, 2, 3]], clusters[[0, 2, 3]],
                           Ts[[0, 2, 3]], landmarks, 5.0) is None
    assert landmarks.n_landmarks == n_before
    # two from either side plus the grazing one: split, grazing row removed
    split = split_two_sided(np.full(5, lm), np.arange(5), clusters, clusters, Ts, landmarks, 5.0)
    assert split is not None and split.n_two_sided == 1
    assert split.scan.tolist() == [0, 1, 3, 4]
    a, b, a2, b2 = split.landmark.tolist()
    assert a == a2 and b == b2 and {a, b} == {lm, n_before}  # room A's face and room B's face
    assert split.n_points_dropped == 40
    assert landmarks.n_landmarks == n_before + 1
    np.testing.assert_allclose(np.abs(landmarks.normal_world[[lm, n_before], 1]), 1.0, atol=1e-9)
    np.testing.assert_allclose(sorted(landmarks.centroid_world[[lm, n_before], 1]),
                               [WALL_Y_M, WALL_Y_M + THICKNESS_M], atol=1e-9)


def _translation(M: np.ndarray) -> np.ndarray:
    """M with its rotation removed (the clusters above are world points minus the sensor position)."""
    out = np.eye(4)
    out[:3, 3] = M[:3, 3]
    return out
