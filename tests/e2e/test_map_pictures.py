"""Pictures and map outputs a person looks at: the refine overview (its panels differ where the
poses do), `pa view --png` (Open3D offscreen or the matplotlib fallback), and `pa refine`'s map
with every point (--map-voxel-m 0), intensities, times, and no point beyond the odometry's range."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pa_cli.io.maps import MapCloud, read_map, write_map
from pa_cli.io.plots import axes_pixels, figure_rgba, overview_figure
from pa_cli.io.trajectory import write_kitti
from pa_testing.room_scene import N_SCANS, ground_truth_poses, room_scans_scan_frame

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _png_pixels(path) -> np.ndarray:
    """The PNG at `path` as an (H, W, 3 or 4) float array, after checking it is a PNG of some size."""
    from matplotlib.image import imread

    assert path.read_bytes()[:8] == PNG_MAGIC and path.stat().st_size > 20_000
    return imread(path)


def _not_blank(pixels: np.ndarray) -> None:
    assert min(pixels.shape[:2]) >= 400
    assert pixels[..., :3].std() > 0.05  # a blank or one-colour picture has (nearly) none


def _panel(fig, name: str) -> np.ndarray:
    ax = next(a for a in fig.axes if a.get_label() == name)
    return axes_pixels(fig, ax)[..., :3].astype(float)


@pytest.fixture(scope="module")
def room():
    return room_scans_scan_frame(n_points=4000), ground_truth_poses()


def _raster(fig, name: str) -> np.ndarray:
    """The image array a slice panel shows (counts per cell, before the grey scale)."""
    return np.asarray(next(a for a in fig.axes if a.get_label() == name).images[0].get_array())


def _changed_pixels(fig) -> float:
    """The share of the slice panels' pixels that differ between before and after."""
    before, after = _panel(fig, "before"), _panel(fig, "after")
    assert before.shape == after.shape
    assert before.std() > 10 and after.std() > 10  # walls on white, not blank
    return float((np.abs(before - after).max(axis=2) > 40).mean())


def test_overview_panels_are_equal_for_equal_poses_and_differ_where_poses_differ(room):
    scans, T = room
    same = overview_figure(scans, T, T.copy())
    assert np.array_equal(_raster(same, "before"), _raster(same, "after"))
    moved = T.copy()
    moved[5:, :3, 3] += [0.3, -0.2, 0.0]  # the second half of the run shifted by 36 cm
    fig = overview_figure(iter(scans), T, moved)  # an iterator: read once
    before, after = _raster(fig, "before"), _raster(fig, "after")
    assert (before != after).mean() > 0.3 * (before > 0).mean()  # the shifted walls fall in other cells
    # on screen: the equal panels differ only by the resampling at their own pixel offsets
    assert _changed_pixels(fig) > 3 * _changed_pixels(same)
    assert {a.get_label() for a in fig.axes} >= {"before", "after", "correction"}
    assert "gt" not in {a.get_label() for a in fig.axes}


def test_overview_with_ground_truth_errors_is_a_png_with_content(room, tmp_path):
    from pa_cli.io.plots import save_png

    scans, T = room
    moved = T.copy()
    moved[:, 0, 3] += np.linspace(0.0, 0.5, N_SCANS)
    curves = [("initial", np.arange(N_SCANS, dtype=float), np.linspace(0.0, 0.5, N_SCANS)),
              ("refined", np.arange(N_SCANS, dtype=float), np.full(N_SCANS, 0.01))]
    fig = overview_figure(scans, moved, T, time_s=100.0 + 0.1 * np.arange(N_SCANS), gt_errors=curves)
    assert "gt" in {a.get_label() for a in fig.axes}
    _not_blank(figure_rgba(fig).astype(float) / 255)
    save_png(fig, tmp_path / "overview.png")
    _not_blank(_png_pixels(tmp_path / "overview.png"))
    with pytest.raises(Exception, match="--force"):
        save_png(fig, tmp_path / "overview.png")


@pytest.fixture(scope="module")
def map_file(tmp_path_factory, room):
    """A PLY map of the room (no intensities) with its trajectory next to it."""
    scans, T = room
    folder = tmp_path_factory.mktemp("view")
    points = np.vstack([s @ T[k, :3, :3].T + T[k, :3, 3] for k, s in enumerate(scans)])
    scan_index = np.repeat(np.arange(N_SCANS, dtype=np.int32), [len(s) for s in scans])
    write_map(folder / "room.ply", MapCloud(points, scan_index, 100.0 + 0.1 * scan_index.astype(float)))
    write_kitti(folder / "room_poses_kitti.txt", T)
    return folder / "room.ply"


def test_view_png_falls_back_to_matplotlib_without_an_offscreen_renderer(run_pa, map_file, tmp_path, monkeypatch):
    from pa_cli.runtime.open3d_preload import open3d

    def no_renderer(*args, **kwargs):
        raise RuntimeError("Failed to load vulkan library!")  # what a headless machine without drivers says

    monkeypatch.setattr(open3d().visualization.rendering, "OffscreenRenderer", no_renderer)
    pictures = {}
    for color in ("scan", "height", "time"):
        png = tmp_path / f"{color}.png"
        code, _, err = run_pa("view", map_file, "--color", color, "--png", png)
        assert code == 0, err
        assert "rendered by matplotlib" in err
        pictures[color] = _png_pixels(png)
        _not_blank(pictures[color])
    assert not np.array_equal(pictures["scan"], pictures["height"])  # the colouring shows


def test_view_png_renders_with_what_the_machine_has(run_pa, map_file, tmp_path):
    png = tmp_path / "view.png"
    code, _, err = run_pa("view", map_file, "--png", png)
    assert code == 0, err
    assert "rendered by open3d" in err or "rendered by matplotlib" in err
    _not_blank(_png_pixels(png))


def test_view_errors_exit_1(run_pa, map_file, tmp_path):
    code, _, err = run_pa("view", map_file, "--color", "intensity", "--png", tmp_path / "v.png")
    assert code == 1 and "no per-point intensity" in err and "--color scan" in err and "Traceback" not in err
    code, _, err = run_pa("view", tmp_path / "missing.ply", "--png", tmp_path / "v.png")
    assert code == 1 and "not found" in err
    (tmp_path / "v.png").write_bytes(b"keep")
    code, _, err = run_pa("view", map_file, "--png", tmp_path / "v.png")
    assert code == 1 and "--force" in err and (tmp_path / "v.png").read_bytes() == b"keep"


def test_view_without_a_display_asks_for_png(run_pa, map_file, monkeypatch):
    for name in ("DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    code, _, err = run_pa("view", map_file)
    assert code == 1 and "no display" in err and "--png" in err


CONFIG = ("sensor: {max_range_m: 30.0, min_range_m: 0.2}\n"
          "scene: {plane_voxel_m: 1.0}\nrefine: {max_rounds: 2}\nmap: {voxel_m: 0.1}\n")


def test_refine_map_keeps_every_point_intensity_and_time_and_drops_far_points(run_pa, room, tmp_path):
    from pa_cli.io.scans import write_pcd

    scans, T = room
    folder = tmp_path / "scans"
    folder.mkdir()
    rng = np.random.default_rng(3)
    n_in_range = 0
    for k, points in enumerate(scans):
        far = rng.normal(size=(5, 3))
        far *= 175.0 / np.linalg.norm(far, axis=1, keepdims=True)  # outliers at 175 m
        intensity = 10.0 * k + rng.random(len(points) + 5)
        write_pcd(folder / f"{k:06d}.pcd", np.vstack([points, far]), intensity=intensity)
        n_in_range += int((np.linalg.norm(points, axis=1) >= 0.2).sum())
    (tmp_path / "times.txt").write_text("".join(f"{100.0 + 0.1 * k:.6f}\n" for k in range(N_SCANS)))
    write_kitti(tmp_path / "gt.txt", T)
    (tmp_path / "cfg.yaml").write_text(CONFIG)
    out = tmp_path / "room.pcd"
    code, _, err = run_pa("refine", folder, "--out", out, "--config", tmp_path / "cfg.yaml", "--poses",
                          tmp_path / "gt.txt", "--gt", tmp_path / "gt.txt", "--map-voxel-m", "0")
    assert code == 0, err
    # the summary says how the map was thinned and what it holds
    assert "every point" in err and "range 0.2-30 m" in err and "scan, intensity, time" in err
    cloud = read_map(out)
    assert len(cloud.points_world) == n_in_range  # every point within the range, none of the far ones
    assert np.linalg.norm(cloud.points_world - T[cloud.scan_index, :3, 3], axis=1).max() <= 30.0
    assert np.array_equal(np.floor(cloud.intensity / 10.0).astype(int), cloud.scan_index)
    assert np.allclose(cloud.time_s, 100.0 + 0.1 * cloud.scan_index)
    report = json.loads(out.with_name("room_report.json").read_text())
    assert report["map"]["voxel_m"] == 0 and report["map"]["n_out_of_range"] == 5 * N_SCANS + (
        sum(len(s) for s in scans) - n_in_range)
    overview = out.with_name("room_overview.png")
    assert report["outputs"]["overview_png"] == str(overview)
    _not_blank(_png_pixels(overview))
    code, _, err = run_pa("refine", folder, "--out", out, "--config", tmp_path / "cfg.yaml", "--poses",
                          tmp_path / "gt.txt")
    assert code == 1 and "--force" in err
