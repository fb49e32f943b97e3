"""`pa simulate` realism: each option changes what it should and nothing else; off, nothing changes.

Most checks compare two runs ray by ray: the same scene, seed and poses with and without one
option (range noise off where the comparison must be exact). A ray is identified by its column
and beam, recovered from the direction of its point.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from pa_cli.simulate import SimOptions, Simulator, build_problem_from_labels, make_scene, simulate_sequence
from pa_cli.simulate.effects import MIXED_PIXEL_MIN_STEP_M, mix_edge_returns
from pa_cli.simulate.scenes import SceneFeatures
from pa_cli.simulate.sensor import REALISTIC
from pa_cli.simulate.streetscape import ROAD_UNDULATION_WAVELENGTH_M

SMALL = ["--scans", "2", "--azimuth-steps", "256"]
OFF_FLAGS = ["--vegetation", "0", "--no-curved-cars", "--road-camber-m", "0", "--road-undulation-m", "0",
             "--no-facade-relief", "--no-facade-gaps", "--range-noise-per-m", "0", "--point-noise-m", "0",
             "--mixed-pixels", "0", "--dropout", "0"]
OPTION_KEYS_BEFORE = {"azimuth_steps", "beams", "max_range_m", "min_range_m", "motion_distortion", "path",
                      "range_noise_m", "scans", "scene", "seed", "step_m", "vfov_deg"}


def _world(points_scan: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points_scan @ T[:3, :3].T + T[:3, 3]


def _by_ray(seq, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Scan k as arrays over every ray (column-major, like the simulator): range (NaN: no return),
    label (-2: no return) and the point (NaN rows: no return)."""
    opt = seq.options
    p = seq.scans[k].points_scan
    r = np.linalg.norm(p, axis=1)
    column = np.round(np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * np.pi) / (2 * np.pi / opt.azimuth_steps))
    elev_step = np.deg2rad(opt.vfov_deg) / (opt.beams - 1)
    beam = np.round((np.arcsin(p[:, 2] / r) + np.deg2rad(opt.vfov_deg) / 2) / elev_step)
    ray = (column.astype(np.int64) % opt.azimuth_steps) * opt.beams + beam.astype(np.int64)
    n = opt.azimuth_steps * opt.beams
    assert len(np.unique(ray)) == len(ray)  # one return per ray
    ranges, labels, points = np.full(n, np.nan), np.full(n, -2, np.int32), np.full((n, 3), np.nan)
    ranges[ray], labels[ray], points[ray] = r, seq.scans[k].labels, p
    return ranges, labels, points


def _signed_dist(points_world: np.ndarray, labels: np.ndarray, planes: np.ndarray) -> np.ndarray:
    pl = planes[labels]
    return np.einsum("ij,ij->i", pl[:, :3], points_world) + pl[:, 3]


def _street(**changes) -> SimOptions:
    return SimOptions(**{"scene": "street", "scans": 3, "beams": 16, "azimuth_steps": 512, "range_noise_m": 0.0,
                         "seed": 4, **changes})


# ---------------------------------------------------------------------------- off: as before


@pytest.mark.parametrize("name", ["office", "street", "town", "blocks", "avenue"])
def test_features_off_leave_the_scene_as_it_was(name):
    plain, off = make_scene(name).mesh, make_scene(name, SceneFeatures()).mesh
    for field in ("vertices", "triangles", "triangle_label", "planes_world"):
        assert np.array_equal(getattr(plain, field), getattr(off, field))
    assert make_scene(name).vegetation is None and make_scene(name).ground_height is None


def test_options_off_give_byte_identical_files(tmp_path, run_pa):
    """Every realism flag at its off value writes exactly what no flag writes, meta.json included
    (its options hold only the keys of before)."""
    for name, extra in (("plain", []), ("off", OFF_FLAGS)):
        code, _, err = run_pa("simulate", "street", tmp_path / name, *SMALL, "--seed", "3", "--motion-distortion",
                              *extra)
        assert code == 0, err
    files = {name: {str(p.relative_to(tmp_path / name)): p.read_bytes()
                    for p in sorted((tmp_path / name).rglob("*")) if p.is_file()} for name in ("plain", "off")}
    assert files["plain"] == files["off"]
    meta = json.loads(files["plain"]["meta.json"])
    assert set(meta["options"]) == OPTION_KEYS_BEFORE


def test_realistic_runs_are_deterministic_and_differ_by_seed(tmp_path, run_pa):
    for name, seed in (("a", "5"), ("b", "5"), ("c", "6")):
        code, _, err = run_pa("simulate", "street", tmp_path / name, *SMALL, "--realistic", "--seed", seed)
        assert code == 0, err
    read = [(tmp_path / name / "scans" / "000001.pcd").read_bytes() for name in "abc"]
    assert read[0] == read[1] and read[0] != read[2]


# ---------------------------------------------------------------------------- --realistic and errors


def test_realistic_fills_what_is_not_given(tmp_path, run_pa):
    code, _, err = run_pa("simulate", "street", tmp_path / "s", *SMALL, "--realistic", "--dropout", "0",
                          "--no-curved-cars")
    assert code == 0, err
    options = json.loads((tmp_path / "s" / "meta.json").read_text())["options"]
    assert options["realistic"] is True
    for key, value in REALISTIC.items():
        assert options[key] == {"dropout": 0.0, "curved_cars": False}.get(key, value), key
    # A scene without a street takes the sensor effects only.
    code, _, err = run_pa("simulate", "office", tmp_path / "o", *SMALL, "--realistic")
    assert code == 0, err
    options = json.loads((tmp_path / "o" / "meta.json").read_text())["options"]
    assert options["vegetation"] == 0.0 and options["curved_cars"] is False and options["road_camber_m"] == 0.0
    assert options["mixed_pixels"] == 0.02 and options["dropout"] == 0.05 and options["range_noise_per_m"] == 0.001


@pytest.mark.parametrize("args, needle", [
    (["office", "--vegetation", "0.3"], "--vegetation"),
    (["hall", "--curved-cars"], "--curved-cars"),
    (["town", "--road-camber-m", "0.1"], "--road-camber-m"),
    (["street", "--vegetation", "1.5"], "--vegetation"),
    (["street", "--dropout", "1"], "--dropout"),
    (["street", "--mixed-pixels", "-0.1"], "--mixed-pixels"),
    (["street", "--road-undulation-m", "0.5"], "--road-undulation-m"),
    (["street", "--range-noise-per-m", "nan"], "--range-noise-per-m"),
    (["hall", "--path", "circuit"], "--path"),
])
def test_bad_realism_arguments_are_usage_errors(tmp_path, run_pa, args, needle):
    scene, *rest = args
    code, _, err = run_pa("simulate", scene, tmp_path / "out", *rest)
    assert code == 2 and needle in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- vegetation


def _inside_vegetation(points_world: np.ndarray, veg, tol: float = 1e-6) -> np.ndarray:
    inside = np.zeros(len(points_world), dtype=bool)
    for center, semi in zip(veg.crown_center, veg.crown_semi_axes, strict=True):
        inside |= np.sum(((points_world - center) / semi) ** 2, axis=1) <= 1 + tol
    for lo, hi in zip(veg.hedge_lo, veg.hedge_hi, strict=True):
        inside |= np.all((points_world >= lo - tol) & (points_world <= hi + tol), axis=1)
    return inside


def test_vegetation_returns_are_unlabelled_scatter_that_moves_between_scans():
    bare = simulate_sequence(_street())
    leafy = simulate_sequence(_street(vegetation=0.4))
    reseeded = simulate_sequence(_street(vegetation=0.4, seed=5))
    veg = Simulator(_street(vegetation=0.4)).scene.vegetation
    assert len(veg.crown_center) > 5 and len(veg.hedge_lo) > 5
    n_leaf = 0
    for k in range(3):
        r0, l0, _ = _by_ray(bare, k)
        r1, l1, p1 = _by_ray(leafy, k)
        r2, _, _ = _by_ray(reseeded, k)
        changed = ~((r0 == r1) | (np.isnan(r0) & np.isnan(r1)))
        # A changed ray returns earlier than the bare mesh, off any plane, inside a crown or hedge
        # or on a trunk (a vertical cylinder under a crown, at most 0.25 m across).
        assert np.all(l1[changed] == -1)
        assert np.all(np.isnan(r0[changed]) | (r1[changed] < r0[changed]))
        pw = _world(p1[changed], leafy.T_world_scan[k])
        trunk = np.linalg.norm(pw[:, None, :2] - veg.crown_center[None, :, :2], axis=2).min(axis=1) < 0.26
        leaf = _inside_vegetation(pw, veg)
        assert np.all(leaf | trunk) and leaf.mean() > 0.8
        # Every other ray is exactly as without vegetation.
        same = ~changed
        assert np.array_equal(l1[same], l0[same])
        n_leaf += int(leaf.sum())
        # Another draw (seed): the leaves return elsewhere, the mesh returns stay.
        leaf2 = _inside_vegetation(_world(_by_ray(reseeded, k)[2], reseeded.T_world_scan[k]), veg)
        both = changed & leaf2
        assert np.mean(r1[both] != r2[both]) > 0.9
    assert n_leaf > 500


def test_vegetation_covers_the_set_share_of_the_street():
    for share in (0.2, 0.6):
        veg = make_scene("street", SceneFeatures(vegetation=share)).vegetation
        xs = np.r_[veg.crown_center[:, 0], (veg.hedge_lo[:, 0] + veg.hedge_hi[:, 0]) / 2]
        pieces = {(int(np.floor((x + 20.0) / 10.0)), side) for x, side in
                  zip(xs, np.sign(np.r_[veg.crown_center[:, 1], veg.hedge_lo[:, 1]]), strict=True)}
        assert len(pieces) == 2 * round(share * 19)  # 19 pieces of 10 m a side from x -20 to 170


# ---------------------------------------------------------------------------- road


def test_camber_and_undulation_shape_the_road_by_the_set_amounts():
    camber, swell = 0.1, 0.03
    flat = simulate_sequence(_street())
    shaped = simulate_sequence(_street(road_camber_m=camber, road_undulation_m=swell))
    sim = Simulator(_street(road_camber_m=camber, road_undulation_m=swell))
    rows, z = [], []
    for seq, is_shaped in ((flat, False), (shaped, True)):
        for k in range(3):
            scan, T = seq.scans[k], seq.T_world_scan[k]
            pw = _world(scan.points_scan, T)
            road = (np.abs(pw[:, 1]) < 3.6) & (pw[:, 2] < 0.2)  # clear of the wheels
            if not is_shaped:
                assert np.abs(pw[road, 2]).max() < 1e-4  # the flat road is the ground plane z = 0
                continue
            assert np.all(scan.labels[road] == -1)  # a curved road is no plane
            x, y = pw[road, 0], pw[road, 1]
            phase = 2 * np.pi * x / ROAD_UNDULATION_WAVELENGTH_M
            rows.append(np.column_stack([np.ones_like(x), (y / 6.0) ** 2, np.sin(phase), np.cos(phase)]))
            z.append(pw[road, 2])
            # The sensor rides the road: always 1.8 m above the surface under it.
            np.testing.assert_allclose(T[2, 3] - sim.scene.ground_height(T[0, 3], T[1, 3]), 1.8, atol=1e-12)
            lab = scan.labels >= 0
            assert np.abs(_signed_dist(pw[lab], scan.labels[lab], seq.planes_world)).max() < 1e-9
    coef, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(z), rcond=None)
    np.testing.assert_allclose(coef, [0.0, -camber, swell, 0.0], atol=1.5e-3)


# ---------------------------------------------------------------------------- sensor effects


def _along_ray_errors(seq) -> tuple[np.ndarray, np.ndarray]:
    """Range errors of the labelled points against their true planes, and their ranges."""
    errors, ranges = [], []
    for scan, T in zip(seq.scans, seq.T_world_scan, strict=True):
        lab = scan.labels >= 0
        p = scan.points_scan[lab]
        r = np.linalg.norm(p, axis=1)
        normals = seq.planes_world[scan.labels[lab], :3] @ T[:3, :3]
        cos = np.abs(np.einsum("ij,ij->i", normals, p / r[:, None]))
        d = _signed_dist(_world(p, T), scan.labels[lab], seq.planes_world)
        ok = cos > 0.2
        errors.append(d[ok] / cos[ok])
        ranges.append(r[ok])
    return np.concatenate(errors), np.concatenate(ranges)


@pytest.mark.parametrize("per_m", [0.0, 0.001])
def test_range_noise_grows_with_range_as_set(per_m):
    seq = simulate_sequence(SimOptions(scene="hall", scans=3, beams=16, azimuth_steps=1024, range_noise_m=0.01,
                                       range_noise_per_m=per_m, seed=2))
    e, r = _along_ray_errors(seq)
    assert len(e) > 30_000 and r.max() > 40.0
    # E|e| = sqrt(2/pi) sigma(r): a straight line fit of |e| sqrt(pi/2) against the range.
    slope, intercept = np.polyfit(r, np.abs(e) * np.sqrt(np.pi / 2), 1)
    assert abs(intercept - 0.01) < 0.001
    assert abs(slope - per_m) < 0.0001


def test_point_noise_is_isotropic_and_moves_nothing_else():
    base = SimOptions(scene="hall", scans=2, beams=16, azimuth_steps=512, range_noise_m=0.0, seed=1)
    clean = simulate_sequence(base)
    noisy = simulate_sequence(replace(base, point_noise_m=0.02))
    offsets = np.vstack([b.points_scan - a.points_scan for a, b in zip(clean.scans, noisy.scans, strict=True)])
    for a, b in zip(clean.scans, noisy.scans, strict=True):
        assert np.array_equal(a.labels, b.labels)
    assert len(offsets) > 10_000
    np.testing.assert_allclose(np.cov(offsets.T), 0.02**2 * np.eye(3), atol=0.06 * 0.02**2)
    assert np.abs(offsets.mean(axis=0)).max() < 5 * 0.02 / np.sqrt(len(offsets))


def test_dropouts_remove_the_set_share_and_move_nothing():
    base = SimOptions(scene="office", scans=3, beams=16, azimuth_steps=512, seed=6)  # default 1 cm noise
    full = simulate_sequence(base)
    thinned = simulate_sequence(replace(base, dropout=0.1))
    n_full = n_kept = 0
    for k in range(3):
        r0, l0, p0 = _by_ray(full, k)
        r1, l1, p1 = _by_ray(thinned, k)
        kept = np.isfinite(r1)
        assert np.all(np.isfinite(r0[kept]))  # no new returns
        assert np.array_equal(p1[kept], p0[kept]) and np.array_equal(l1[kept], l0[kept])  # none moved
        n_full += int(np.isfinite(r0).sum())
        n_kept += int(kept.sum())
    assert abs(1 - n_kept / n_full - 0.1) < 0.01


def test_mixed_pixels_lie_between_the_two_surfaces_of_an_edge():
    clean = simulate_sequence(_street())
    mixed = simulate_sequence(_street(mixed_pixels=0.02))
    B, A = 16, 512
    for k in range(3):
        r0, l0, _ = _by_ray(clean, k)
        r1, l1, _ = _by_ray(mixed, k)
        assert np.array_equal(np.isfinite(r0), np.isfinite(r1))  # mixing moves returns, never adds or drops
        moved = np.flatnonzero(np.isfinite(r0) & (r0 != r1))
        assert len(moved) == round(0.02 * np.isfinite(r0).sum())
        assert np.all(l1[moved] == -1)
        same = np.setdiff1d(np.flatnonzero(np.isfinite(r0)), moved)
        assert np.array_equal(l1[same], l0[same])
        column, beam = moved // B, moved % B
        between = np.zeros(len(moved), dtype=bool)
        for step in (-1, 1):
            rn = r0[((column + step) % A) * B + beam]
            lo, hi = np.fmin(r0[moved], rn), np.fmax(r0[moved], rn)
            between |= (hi - lo >= MIXED_PIXEL_MIN_STEP_M) & (lo < r1[moved]) & (r1[moved] < hi)
        assert between.all()


def test_mixed_pixels_take_all_edges_when_asked_for_more():
    ranges = np.array([5.0, 5.0, 9.0, 9.0, 9.0, 9.0, 9.0, 9.0])  # one beam row of 8 columns: two edges
    neighbours = np.column_stack([(np.arange(8) - 1) % 8, (np.arange(8) + 1) % 8])
    out, mixed = mix_edge_returns(ranges, np.ones(8, bool), neighbours, 0.9, np.random.default_rng(0))
    assert mixed.tolist() == [True, True, True, False, False, False, False, True]
    assert np.all((out[mixed] > 5.0) & (out[mixed] < 9.0))


# ---------------------------------------------------------------------------- cars and facades


def test_curved_cars_replace_the_box_cars_with_unlabelled_curved_bodies():
    boxes, curved = make_scene("street").mesh, make_scene("street", SceneFeatures(curved_cars=True)).mesh

    def car_zone(mesh) -> np.ndarray:
        c = mesh.vertices[mesh.triangles].mean(axis=1)
        return (np.abs(np.abs(c[:, 1]) - 4.9) < 1.0) & (c[:, 2] < 1.6) & (c[:, 0] > 1.0) & (c[:, 0] < 133.0)

    zone = car_zone(curved)
    assert zone.sum() > 30 * 500 and np.all(curved.triangle_label[zone] == -1)
    assert np.any(boxes.triangle_label[car_zone(boxes)] >= 0)  # the box cars had planes
    # Curved: the triangle normals of the bodies point every way, not in 6 directions.
    tri = curved.vertices[curved.triangles[zone]]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    assert len(np.unique(np.round(np.abs(normals), 2), axis=0)) > 300
    # Only car planes went: every plane of the curved street is a plane of the box street.
    gaps = np.abs(curved.planes_world[:, None, :] - boxes.planes_world[None, :, :]).max(axis=2)
    assert gaps.min(axis=1).max() < 1e-12 and len(curved.planes_world) < len(boxes.planes_world)


def _front_planes(mesh, side: int) -> np.ndarray:
    """Distances from the centre line of the planes facing the street on one side (|n_y| = 1)."""
    pl = mesh.planes_world
    facing = np.abs(np.abs(pl[:, 1]) - 1) < 1e-12
    y = -pl[facing, 3] / pl[facing, 1]
    return np.sort(side * y[side * y > 9.5])


def test_facade_relief_steps_the_fronts_by_ten_to_fifty_cm():
    plain = make_scene("street").mesh
    relief = make_scene("street", SceneFeatures(facade_relief=True)).mesh
    for side in (-1, 1):
        fronts = _front_planes(plain, side)
        stepped = _front_planes(relief, side)
        for front in (10.0, 11.5, 13.0):
            for step in (0.1, 0.2, 0.3, 0.4, 0.5):
                assert np.min(np.abs(stepped - (front + step))) < 1e-9
        assert set(np.round(fronts, 6)) <= set(np.round(stepped, 6))
    # Balconies: slabs and parapets 0.6-1.2 m out in front of the facades.
    assert len(relief.planes_world) > len(plain.planes_world) + 40
    lab = relief.triangle_label >= 0
    tri = relief.vertices[relief.triangles[lab]]
    assert np.abs(_signed_dist(tri.reshape(-1, 3), np.repeat(relief.triangle_label[lab], 3),
                               relief.planes_world)).max() < 1e-9


def _facade_gaps_m(mesh, side: int) -> np.ndarray:
    """Lengths of the stretches without a building front on one side of the street (x -20 to 170)."""
    c = mesh.vertices[mesh.triangles]
    tall = (c[:, :, 2].max(axis=1) > 6.0) & (side * c[:, :, 1].min(axis=1) > 9.9) & (np.ptp(c[:, :, 1], axis=1) > 5)
    spans = sorted((float(t[:, 0].min()), float(t[:, 0].max())) for t in c[tall])
    gaps, reach = [], -20.0
    for a, b in spans:
        if a > reach + 1e-6:
            gaps.append(a - reach)
        reach = max(reach, b)
    return np.array(gaps)


def test_facade_gaps_leave_open_lots_of_a_building_or_so():
    plain = make_scene("street").mesh
    gappy = make_scene("street", SceneFeatures(facade_gaps=True)).mesh
    lots = []
    for side in (-1, 1):
        assert _facade_gaps_m(plain, side).max() <= 5.0  # alleys only
        gaps = _facade_gaps_m(gappy, side)
        lots += gaps[gaps > 5.0].tolist()
    # A lot is one left-out building (12-26 m) with the alleys beside it (0-5 m each).
    assert len(lots) >= 3 and min(lots) >= 12.0 and max(lots) <= 36.0


# ---------------------------------------------------------------------------- new scenes and ground truth


def test_hall_is_walls_and_floor_and_its_sharp_path_turns_up_to_22_5_deg_per_scan():
    from pa_cli.runtime.open3d_preload import open3d

    o3d = open3d()
    scene = make_scene("hall")
    assert np.all(scene.mesh.triangle_label >= 0)  # nothing but planes
    lo, hi = scene.mesh.vertices.min(axis=0), scene.mesh.vertices.max(axis=0)
    np.testing.assert_allclose(hi[:2] - lo[:2], [60.6, 30.6])
    sim = Simulator(SimOptions(scene="hall", path="sharp", azimuth_steps=64))
    assert sim.options.step_m == 0.9
    T = sim.path.poses(np.arange(0.0, sim.path.length_m, 0.9))
    turn = np.degrees(np.abs(np.diff(np.unwrap(np.arctan2(T[:, 1, 0], T[:, 0, 0])))))
    assert 21.0 < turn.max() <= 22.5
    for scene_name, path in (("hall", "loop"), ("hall", "sharp"), ("avenue", "loop")):
        sim = Simulator(SimOptions(scene=scene_name, path=path, azimuth_steps=64, realistic=True))
        xyz = sim.path.poses(np.linspace(0.0, sim.path.length_m, 3000))[:, :3, 3]
        assert sim._raycaster.compute_distance(o3d.core.Tensor(xyz.astype(np.float32))).numpy().min() > 0.25


def test_avenue_has_few_facades_and_repeats_itself():
    mesh = make_scene("avenue").mesh
    c = mesh.vertices[mesh.triangles]
    tall = (c[:, :, 2].max(axis=1) > 10.0) & (np.ptp(c[:, :, 1], axis=1) > 5)
    for side in (-1, 1):
        on_side = tall & (side * c[:, :, 1].min(axis=1) > 0) & (np.ptp(c[:, :, 0], axis=1) > 1)
        spans = sorted({(round(float(t[:, 0].min()), 6), round(float(t[:, 0].max()), 6)) for t in c[on_side]})
        # Four identical buildings 80 m apart: a facade along a quarter of the 320 m.
        assert len(spans) == 4 and {round(b - a, 6) for a, b in spans} == {22.0}
        assert set(np.round(np.diff([a for a, _ in spans]), 6)) == {80.0}
        assert 11.5 in np.round(_front_planes(mesh, side), 6)


def test_ground_truth_labels_only_true_plane_points_in_a_realistic_street():
    opt = SimOptions(scene="street", scans=3, beams=32, azimuth_steps=512, realistic=True, seed=8)
    seq = simulate_sequence(opt)
    bare = simulate_sequence(SimOptions(scene="street", scans=3, beams=32, azimuth_steps=512, seed=8))
    o = seq.options
    n_labelled = 0
    for scan, scan_bare, T in zip(seq.scans, bare.scans, seq.T_world_scan, strict=True):
        lab = scan.labels >= 0
        r = np.linalg.norm(scan.points_scan[lab], axis=1)
        d = _signed_dist(_world(scan.points_scan[lab], T), scan.labels[lab], seq.planes_world)
        # Labelled points are on their plane within their range noise: no leaf, mixed pixel or car.
        assert np.all(np.abs(d) < 6.5 * (o.range_noise_m + o.range_noise_per_m * r) + 1e-4)
        assert np.mean(~lab) > 2 * np.mean(scan_bare.labels < 0)
        n_labelled += int(lab.sum())
    problem = build_problem_from_labels(seq, min_points=10)
    assert 0.9 * n_labelled < problem.n_points <= n_labelled


def test_rig_lidars_with_a_partial_field_of_view_take_the_effects():
    from pa_cli.simulate.rig import MountedSimulator

    plain = MountedSimulator(_street(), np.eye(4), hfov_deg=180.0).scan(1)
    scan = MountedSimulator(_street(mixed_pixels=0.05, vegetation=0.4), np.eye(4), hfov_deg=180.0).scan(1)
    assert np.all(np.abs(np.arctan2(scan.points_scan[:, 1], scan.points_scan[:, 0])) <= np.pi / 2 + 1e-9)
    assert np.sum(scan.labels < 0) > np.sum(plain.labels < 0) + 0.05 * len(plain.labels)
