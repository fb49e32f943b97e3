"""`pa refine` hardening: Ctrl-C, messages printed verbatim, every input checked before any work,
one timestamp message, stage times counted once, finished progress bars, warnings as log records.

Each case asserts the exit code, a message naming the file and the problem, no traceback
without --debug, and no output left behind."""

from __future__ import annotations

import json
import shutil
import warnings

import numpy as np
import pytest

from pa_cli.errors import SolverError
from pa_cli.refine.outputs import RefineOutputs
from pa_cli.refine.pipeline import RefinePipeline
from pa_testing.room_scene import N_SCANS, write_room_folder

CONFIG = ("sensor: {max_range_m: 30.0, min_range_m: 0.2}\nscene: {plane_voxel_m: 1.0}\nrefine: {max_rounds: 2}\n"
          "map: {voxel_m: 0.1}\nadvanced: {kiss_icp: {voxel_size_m: 0.1}}\n")


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    root = write_room_folder(tmp_path_factory.mktemp("room"))
    (root / "cfg.yaml").write_text(CONFIG)
    return root


def _refine(run_pa, room, out_dir, *extra):
    """`pa refine` of the room with the ground-truth poses as --poses (no odometry: fast)."""
    return run_pa("refine", room / "scans", "--out", out_dir / "m.ply", "--config", room / "cfg.yaml",
                  "--poses", room / "gt_kitti.txt", *extra)


def _no_odometry(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("odometry ran before the inputs were checked")

    monkeypatch.setattr("pa_cli.refine.stages.run_kiss_icp", fail)


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def _step_names() -> list[str]:
    from pa_cli.config import PaConfig

    return [step.__name__ for step in RefinePipeline("scans", "m.ply", PaConfig()).steps()]


@pytest.mark.parametrize("stage", [*_step_names(), "write_map"])
def test_ctrl_c_exits_130_and_writes_no_output(run_pa, room, tmp_path, monkeypatch, stage):
    if stage == "write_map":  # inside the write step, with every temporary output open
        monkeypatch.setattr("pa_cli.refine.outputs.write_map", _interrupt)
    else:
        monkeypatch.setattr(RefinePipeline, stage, _interrupt)
    code, out, err = _refine(run_pa, room, tmp_path, "--gt", room / "gt_kitti.txt", "-q")
    assert code == 130 and out == ""
    if stage in ("check_inputs", "open_scans", "load", "open_work"):  # before the work folder
        assert err.strip() == "interrupted"
        assert list(tmp_path.iterdir()) == []
    else:  # no output; the work folder kept for --resume, with a line saying so
        assert err.strip().endswith("interrupted") and "--resume" in err
        assert list(tmp_path.iterdir()) == [tmp_path / "m.work"]


@pytest.mark.parametrize("name", ["a[/x]b", "[bold]nope", "[red]x[/red]"])
def test_error_printer_shows_paths_verbatim(run_pa, tmp_path, name):
    missing = tmp_path / name
    code, _, err = run_pa("refine", missing, "--out", tmp_path / "m.ply")
    assert code == 1 and f"{missing}: scans not found" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_error_printer_keeps_brackets_of_formulas(run_pa, room, tmp_path, monkeypatch):
    def asymmetric(self):
        raise SolverError("problem.npz: cluster 3 is not symmetric; expected [p;1][p;1]^T sums.")

    monkeypatch.setattr(RefinePipeline, "check_inputs", asymmetric)
    code, _, err = _refine(run_pa, room, tmp_path)
    assert code == 1 and "cluster 3 is not symmetric; expected [p;1][p;1]^T sums." in err
    assert list(tmp_path.iterdir()) == []


def test_missing_gt_is_reported_before_odometry(run_pa, room, tmp_path, monkeypatch):
    _no_odometry(monkeypatch)
    gt = tmp_path / "gt_missing.txt"
    code, _, err = run_pa("refine", room / "scans", "--out", tmp_path / "m.ply", "--gt", gt)
    assert code == 1 and str(gt) in err and "not found" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_a_file_given_as_scans_says_it_is_a_file(run_pa, room, tmp_path, monkeypatch):
    _no_odometry(monkeypatch)
    code, _, err = run_pa("refine", room / "gt_kitti.txt", "--out", tmp_path / "m.ply")
    assert code == 1 and f"{room / 'gt_kitti.txt'}: is a file" in err and "not found" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_corrupt_scan_is_reported_before_odometry(run_pa, room, tmp_path, monkeypatch, suffix):
    from pa_cli.io.scans import read_scan

    _no_odometry(monkeypatch)
    scans = tmp_path / "scans"
    shutil.copytree(room / "scans", scans)
    if suffix == ".ply":
        for pcd in sorted(scans.glob("*.pcd")):  # one format per folder: every scan a PLY
            points = read_scan(pcd).points_scan.astype("<f4")
            pcd.unlink()
            header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n" + "".join(
                f"property float {a}\n" for a in "xyz") + "end_header\n"
            pcd.with_suffix(".ply").write_bytes(header.encode() + points.tobytes())
    bad = scans / f"000004{suffix}"
    bad.write_bytes(bad.read_bytes()[:-100])  # truncated binary data
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run_pa("refine", scans, "--out", out / "m.ply", "-q")
    assert code == 1 and f"{bad}:" in err and "truncated" in err and "Traceback" not in err
    assert list(out.iterdir()) == []


def test_ignored_times_file_is_the_only_timestamp_message(run_pa, room, tmp_path):
    folder = tmp_path / "seq"
    shutil.copytree(room / "scans", folder / "scans")
    (folder / "times.txt").write_text("0.0\n0.1\n0.2\n")
    out = tmp_path / "out"
    out.mkdir()
    code, _, err = run_pa("refine", folder / "scans", "--out", out / "m.ply", "--config", room / "cfg.yaml",
                          "--poses", room / "gt_kitti.txt", "-q")
    assert code == 0, err
    message = "".join(err.split())  # log records wrap at the console width, even inside words
    expected = f"{folder / 'times.txt'} has 3 timestamps for {N_SCANS} scans (ignored)"
    assert "".join(expected.split()) in message
    assert "notimes.txt" not in message and message.count("timestamps") == 2
    assert err.strip().splitlines()[-1].startswith("pa refine: verdict ")  # -q keeps the verdict line


def test_stage_times_counted_once_and_bars_finish(room, tmp_path, capsys):
    from pa_cli.cli.tables import refine_summary_table
    from pa_cli.config import load_config
    from pa_cli.io.problem import load_problem

    pipeline = RefinePipeline(room / "scans", tmp_path / "m.ply", load_config(room / "cfg.yaml"),
                              poses=room / "gt_kitti.txt", save_problem=tmp_path / "p.npz", show_progress=True)
    report = pipeline.run()
    # the saved problem holds the refined poses; the solver's problem keeps those it was built at
    assert np.array_equal(load_problem(tmp_path / "p.npz").T_world_scan, pipeline.state.T_current)
    assert not np.array_equal(pipeline.state.rounds.problem.T_world_scan, pipeline.state.T_current)
    written = json.loads(RefineOutputs.from_map_path(tmp_path / "m.ply").report_json.read_text())
    assert written["stage_times_s"] == pytest.approx(report["stage_times_s"], rel=0, abs=0)
    # the stages do not overlap: they add up to at most the run's wall time, which also holds the work between them
    assert sum(report["stage_times_s"].values()) <= written["total_time_s"] == report["total_time_s"]
    table_total = refine_summary_table(report).columns[2]._cells[-1]
    assert table_total == f"{written['total_time_s']:.1f}"
    err = capsys.readouterr().err
    for r in report["rounds"]:
        iterations = r["iterations"]  # of every solve of the round
        bar = [line for line in err.splitlines() if line.startswith(f"adjust {r['round']} ")]
        assert bar and f"{iterations}/{iterations}" in bar[-1], bar


def test_numpy_warnings_become_log_records(run_pa, room, tmp_path, monkeypatch):
    def warn(self):
        np.sqrt(np.array([-1.0]))
        warnings.warn("casting complex values to real", np.exceptions.ComplexWarning, stacklevel=1)

    monkeypatch.setattr(RefinePipeline, "evaluate", warn)
    code, _, err = _refine(run_pa, room, tmp_path, "-q")
    assert code == 0, err
    lines = [line.strip() for line in err.splitlines()]
    assert any(line.startswith("WARNING") and "RuntimeWarning: invalid value encountered in sqrt" in line
               for line in lines)
    assert any("ComplexWarning: casting complex values to real" in line for line in lines)
    assert "np.sqrt(" not in err  # the raw warning format quotes the source line


def test_laz_without_a_backend_is_refused_before_any_work(run_pa, room, tmp_path, monkeypatch):
    import laspy

    _no_odometry(monkeypatch)
    monkeypatch.setattr(laspy.LazBackend, "detect_available", staticmethod(lambda: ()))
    code, _, err = run_pa("refine", room / "scans", "--out", tmp_path / "m.laz")
    assert code == 1 and f"{tmp_path / 'm.laz'}: writing .laz needs a LAZ backend" in err and "lazrs" in err
    assert list(tmp_path.iterdir()) == []
