"""The work folder (`pa_cli.refine.work`): what the rounds hand on survives a write and a read
exactly, the deskew fixed point continues where it stopped, and a folder made for other inputs
is refused."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from pa_cli.config import PaConfig
from pa_cli.errors import InputError, OutputError
from pa_cli.planes.edges import EdgeLabels
from pa_cli.planes.labels import PointLabels
from pa_cli.refine.deskew import DeskewFixedPoint
from pa_cli.refine.memory import SequenceSize, check_adjust_memory, check_sequence_memory
from pa_cli.refine.state import RoundsCarry
from pa_cli.refine.work import (
    WorkFolder,
    config_digest,
    files_identity,
    manifest,
    open_work_folder,
    work_folder_path,
)
from pa_testing.synthetic_problems import make_scene, perturb


def _labels(rng: np.random.Generator, n_scans: int) -> PointLabels:
    n_obs = 7
    return PointLabels(rng.integers(0, 3, n_obs), rng.integers(0, n_scans, n_obs), n_scans,
                       [rng.integers(-1, n_obs, rng.integers(0, 50)).astype(np.int32) for _ in range(n_scans)])


def _trajectory(rng: np.random.Generator, n: int) -> np.ndarray:
    return perturb(np.tile(np.eye(4), (n, 1, 1)), 0.01, 0.1, seed=int(rng.integers(1 << 30)))


def test_a_rounds_carry_is_read_back_exactly(tmp_path):
    rng = np.random.default_rng(0)
    work = WorkFolder(tmp_path)
    records = [{"round": 1, "solver": {"iterations": 4, "cost": 0.1 + 1e-17, "nan": float("inf")}, "planes": {}},
               {"round": 2, "deskew_acceleration": {"contraction": None, "extrapolated": False}}]
    fixed = {"extrapolated": np.array(True), "start": _trajectory(rng, 5), "result": _trajectory(rng, 5),
             "residual_m": np.array(0.1234567890123)}
    edge_labels = _labels(rng, 5)
    on_edges = [np.sort(rng.choice(1000, len(obs), replace=False)).astype(np.int32)
                for obs in edge_labels.observation_of_point]
    edges = EdgeLabels(edge_labels, on_edges, rng.standard_normal((7, 3)), 4)
    carry = RoundsCarry(2, _trajectory(rng, 5), records, _labels(rng, 5), _labels(rng, 5), True,
                        {"round": 1, "scans": [{"scan": 3, "moved_m": 0.2}]}, fixed, rng.standard_normal((5, 6)),
                        edges)
    work.save_carry(carry)
    back = work.load_carry()
    assert back.next_round == 2 and back.frozen is True and back.records == records
    assert back.unsettled_association == carry.unsettled_association
    np.testing.assert_array_equal(back.T_world_scan, carry.T_world_scan)
    np.testing.assert_array_equal(back.association_change, carry.association_change)
    np.testing.assert_array_equal(back.edge_labels.shift_scan_m, edges.shift_scan_m)
    for a, b in zip(back.edge_labels.point_index, on_edges, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert back.edge_labels.n_detected == 4
    for a, b in ((back.labels_initial, carry.labels_initial), (back.labels_final, carry.labels_final),
                 (back.edge_labels.labels, edges.labels)):
        np.testing.assert_array_equal(a.plane_index, b.plane_index)
        np.testing.assert_array_equal(a.scan_index, b.scan_index)
        assert a.n_scans == b.n_scans and len(a.observation_of_point) == len(b.observation_of_point)
        for x, y in zip(a.observation_of_point, b.observation_of_point, strict=True):
            assert x.dtype == y.dtype and np.array_equal(x, y)
    assert set(back.fixed_point) == set(fixed)
    for key, value in fixed.items():
        np.testing.assert_array_equal(back.fixed_point[key], value)
    assert [p.name for p in tmp_path.iterdir()] == ["round.npz"]  # no temporary file left


def test_a_first_round_carry_without_labels_or_memory(tmp_path):
    work = WorkFolder(tmp_path)
    assert work.load_carry() is None and work.load_motions() is None
    T = _trajectory(np.random.default_rng(1), 3)
    work.save_carry(RoundsCarry(1, T, []))
    back = work.load_carry()
    assert back.labels_initial is None and back.labels_final is None and back.fixed_point == {}
    assert back.edge_labels is None
    assert back.association_change is None
    R, t = T[1:, :3, :3], T[1:, :3, 3]
    sigmas = np.random.default_rng(2).uniform(0.001, 0.01, (len(t), 6))
    noise = {"rotation_sigma_deg": [0.1, 0.2, 0.01], "translation_sigma_m": [0.01, 0.005, 0.004], "n_closures": 9}
    work.save_motions(R, t, sigmas, noise)
    R_back, t_back, sigmas_back, noise_back = work.load_motions()
    for a, b in ((R, R_back), (t, t_back), (sigmas, sigmas_back)):
        np.testing.assert_array_equal(a, b)
    assert noise_back == noise
    work.save_motions(R, t, sigmas, None)
    assert work.load_motions()[3] is None


def test_a_carry_is_written_as_it_was_when_saved_and_its_error_comes_at_the_wait(tmp_path, monkeypatch):
    """The carry is written on a thread of its own while the next round runs: the records appended and the poses
    changed after `save_carry` are not in it. A failed write raises at `wait` (and at the next save), not at
    `drain`, which a stopping run calls."""
    import pa_cli.refine.work as work_module

    rng = np.random.default_rng(4)
    work = WorkFolder(tmp_path)
    records, T = [{"round": 1}], _trajectory(rng, 4)
    work.save_carry(RoundsCarry(1, T, records, _labels(rng, 4), _labels(rng, 4)))
    records.append({"round": 2})
    expected_T = T.copy()
    T[:, :3, 3] += 1.0
    work.wait()
    back = work.load_carry()
    assert back.records == [{"round": 1}] and np.array_equal(back.T_world_scan, expected_T)

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(work_module.np, "savez", full_disk)
    work.save_carry(RoundsCarry(2, T, records))
    with pytest.raises(OSError, match="No space"):
        work.wait()
    work.save_carry(RoundsCarry(3, T, records))
    work.drain()  # the error stays with the run that stops for another reason
    assert work.load_carry().next_round == 1  # the last carry written whole


def test_the_deskew_fixed_point_continues_from_its_memory():
    """Rounds fed to one `DeskewFixedPoint` and to one that stopped after two and remembered:
    the same starts and records (the secant step uses the rounds before the stop)."""
    rng = np.random.default_rng(2)
    fixed_star = _trajectory(rng, 6)
    steps = []
    T = _trajectory(rng, 6)
    for _ in range(5):  # a contraction towards fixed_star, r = 0.6, in the translations
        result = T.copy()
        result[:, :3, 3] = fixed_star[:, :3, 3] + 0.6 * (T[:, :3, 3] - fixed_star[:, :3, 3])
        result[:, :3, :3] = fixed_star[:, :3, :3]
        steps.append((T, result))
        T = result
    whole = DeskewFixedPoint(10.0, 0.9)
    expected = [whole.next_start(a, b) for a, b in steps]
    assert any(record["extrapolated"] for _, record in expected)
    first = DeskewFixedPoint(10.0, 0.9)
    got = [first.next_start(a, b) for a, b in steps[:2]]
    later = DeskewFixedPoint(10.0, 0.9)
    later.remember(first.memory())
    got += [later.next_start(a, b) for a, b in steps[2:]]
    for (T_got, record_got), (T_expected, record_expected) in zip(got, expected, strict=True):
        np.testing.assert_array_equal(T_got, T_expected)
        assert record_got == record_expected


def _expected(tmp_path, config=None):
    scans = tmp_path / "scans"
    scans.mkdir(exist_ok=True)
    for k in range(3):
        (scans / f"{k:06d}.pcd").write_bytes(b"x" * (10 + k))
    return manifest(scans, 3, None, None, None, None, config or PaConfig())


def test_open_makes_continues_or_refuses_a_work_folder(tmp_path, caplog):
    path = work_folder_path(tmp_path / "map.ply")
    assert path == tmp_path / "map.work"
    expected = _expected(tmp_path)
    work = open_work_folder(path, expected, resume=False, force=False)
    assert json.loads((path / "manifest.json").read_text()) == expected
    work.save("odometry", {"T_odometry": np.eye(4)[None]})
    with pytest.raises(OutputError, match="--resume.*--force"):
        open_work_folder(path, expected, resume=False, force=False)
    assert open_work_folder(path, expected, resume=True, force=False).load("odometry") is not None
    other = dict(expected, config_digest="another")
    with pytest.raises(InputError, match=r"other inputs \(the config differ.*--force"):
        open_work_folder(path, other, resume=True, force=False)
    assert open_work_folder(path, expected, resume=False, force=True).load("odometry") is None  # started over
    work.remove()
    with caplog.at_level(logging.INFO):
        open_work_folder(path, expected, resume=True, force=False)
    assert "nothing to resume" in caplog.text and (path / "manifest.json").exists()


def test_the_manifest_follows_the_scans_and_the_result_keys_of_the_config(tmp_path):
    expected = _expected(tmp_path)
    scans = tmp_path / "scans"
    (scans / "000001.pcd").write_bytes(b"y" * 99)
    assert files_identity(scans) != expected["scans"]
    config = PaConfig()
    config.execution.memory_budget_gb = 1.0
    config.execution.cache_budget_gb = 0.5
    assert config_digest(config) == config_digest(PaConfig())  # budgets never change a result
    config.refine.max_rounds += 1
    assert config_digest(config) != config_digest(PaConfig())


def test_memory_checks_name_the_stage_the_estimate_and_the_key(caplog):
    config = PaConfig()
    size = SequenceSize.from_files(1000, 1000 * 4096 * 16)
    assert size.n_points == 1000 * 4096
    with caplog.at_level(logging.WARNING):
        assert check_sequence_memory("planes", size, config)  # ~0.3 GB within 8 GB
        assert not caplog.text
        config.execution.memory_budget_gb = 0.01
        for stage in ("odometry", "loops", "planes", "map"):
            assert not check_sequence_memory(stage, size, config)
    text = " ".join(caplog.text.split())
    for stage, key in (("odometry", "execution.cache_budget_gb"), ("loops", "advanced.loops.local_map_voxel_m"),
                       ("planes", "execution.cache_budget_gb"), ("map", "map.voxel_m")):
        assert f"{stage}: expected to hold about" in text and key in text
    assert text.count("above execution.memory_budget_gb = 0.01") == 4
    # 4096 points per scan: the planes stage holds 16 + 24 + 8 + 32 bytes per point and the poses
    planes_gb = float(text.split("planes: expected to hold about ")[1].split(" GB")[0])
    assert planes_gb == pytest.approx((1000 * 4096 * (16 + 24 + 8 + 32) + 1000 * 128) / 1e9, abs=0.006)
    # with loops the odometry keeps its thinned frames for them: at most 12 bytes per point more
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        for enabled in (False, True):
            config.loops.enabled = enabled
            check_sequence_memory("odometry", size, config)
    odometry_gb = [float(part.split(" GB")[0]) for part in caplog.text.split("odometry: expected to hold about ")[1:]]
    assert odometry_gb[1] - odometry_gb[0] == pytest.approx(1000 * 4096 * 12 / 1e9, abs=0.011)


def test_the_adjust_check_counts_the_clusters_and_the_flat_system(caplog):
    problem, _ = make_scene(40, 160, 20, points_per_observation=5, noise_m=0.01, seed=0)
    config = PaConfig()
    config.execution.memory_budget_gb = 1e-9
    flat, hierarchical = config.advanced.solver.model_copy(), config.advanced.solver.model_copy()
    flat.solver, hierarchical.solver = "newton", "hierarchical"
    with caplog.at_level(logging.WARNING):
        assert not check_adjust_memory("adjust 1", problem, flat, config)
        assert not check_adjust_memory("adjust 2", problem, hierarchical, config)
    text = " ".join(caplog.text.split())
    assert "adjust 1: expected" in text and "reduced system of 40 scans" in text
    assert "adjust 2: expected" in text and f"clusters of {problem.n_observations:,} observations" in text
    config.execution.memory_budget_gb = 1.0
    assert check_adjust_memory("adjust 1", problem, flat, config)
