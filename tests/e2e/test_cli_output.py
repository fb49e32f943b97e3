"""What `pa` prints: `--help` at 80 columns, repeated warnings folded, the verdict line of `-q`."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import typer

from pa_cli.cli import app
from pa_cli.refine.pipeline import RefinePipeline
from pa_cli.sources import open_source
from pa_testing.room_scene import room_scans_scan_frame

N_FILES = 4


def _words(text: str) -> str:
    """`text` with every run of white space one space (rich wraps lines at the console width)."""
    return " ".join(text.split())


@pytest.mark.parametrize("command", ["", *typer.main.get_command(app).commands])
def test_help_shows_flags_without_a_value_and_truncates_nothing(run_pa, monkeypatch, command):
    monkeypatch.setenv("COLUMNS", "80")
    code, out, _ = run_pa(*([command] if command else []), "--help")
    assert code == 0
    assert "<bool>" not in out  # typer shows a flag's type as if the flag took a value
    assert "…" not in out  # rich cuts words longer than the help column
    if command == "refine":
        assert "--force " in out and "sensor_msgs/PointCloud2" in out


def test_repeated_warnings_fold_into_one_line_each(capsys):
    from pa_cli.cli.app import folded_warnings, log, setup_logging

    setup_logging(logging.INFO)
    with folded_warnings():
        for k in range(21):
            log.warning("%s: PCD header says POINTS %d but the data holds %d points.", Path(f"{k}.pcd"), 5, 6 + k)
        log.warning("%s: PCD header says POINTS %d but the data holds %d points.", Path("0.pcd"), 5, 6)
        for _ in range(3):
            log.warning("rounds did not settle; raise refine.max_rounds.")
        log.warning("%s: the scan holds no points.", Path("empty.pcd"))
        log.warning("%s: the scan holds no points.", Path("empty.pcd"))  # the same file again: said already
        log.info("%s: an info record is never folded.", Path("a.pcd"))
        log.info("%s: an info record is never folded.", Path("a.pcd"))
    err = capsys.readouterr().err
    lines = [_words(line) for line in err.split("WARNING") if line.strip()]
    assert lines[0] == "0.pcd: PCD header says POINTS 5 but the data holds 6 points."
    assert lines[1] == "rounds did not settle; raise refine.max_rounds."
    assert lines[2].startswith("empty.pcd: the scan holds no points.")
    assert _words(err).count("an info record is never folded") == 2
    assert lines[3:] == ["PCD header says POINTS ... but the data holds ... points. (21 files; first: 0.pcd)",
                         "rounds did not settle; raise refine.max_rounds. (3 times)"]


@pytest.fixture
def bad_headers(tmp_path):
    """N_FILES PCD scans whose header POINTS is short of their data by one point."""
    from pa_cli.io.scans import write_pcd

    scans = tmp_path / "scans"
    scans.mkdir()
    for k, points in enumerate(room_scans_scan_frame(seed=5, n_points=50)[:N_FILES]):
        write_pcd(scans / f"{k}.pcd", points)
        (scans / f"{k}.pcd").write_bytes((scans / f"{k}.pcd").read_bytes() + bytes(12))
    return scans


REPORT = {"summary": {"n_scans": N_FILES, "n_points_on_planes": 100, "n_landmarks": 3, "cost_initial_m2": 1.0,
                      "cost_final_m2": 0.5, "n_rounds": 3, "iterations": 8, "settled": True},
          "input": {}, "stage_times_s": {"load": 1.0}, "total_time_s": 1.0,
          "quality": {"verdict": "improved", "reasons": [],
                      "rms_point_to_plane_m": {"planes_at_initial_poses": {"initial": 0.03, "refined": 0.01},
                                               "planes_at_refined_poses": {"initial": 0.04, "refined": 0.01}}},
          "gt": {"initial": {"ate_rmse_m": 0.0302}, "refined": {"ate_rmse_m": 0.0006}}}


def _reads_the_scans(self: RefinePipeline) -> dict:
    """`RefinePipeline.run` cut to its reads: every header checked, every scan read (their warnings)."""
    source = open_source(self.scans_path)
    source.check()
    for k in range(len(source)):
        source.points(k)
    return REPORT


@pytest.mark.parametrize("quiet", [True, False])
def test_refine_warns_once_per_kind_and_quiet_keeps_the_verdict(run_pa, bad_headers, tmp_path, monkeypatch, quiet):
    monkeypatch.setattr(RefinePipeline, "run", _reads_the_scans)
    code, _, err = run_pa("refine", bad_headers, "--out", tmp_path / "m.ply", *(["-q"] if quiet else []))
    assert code == 0, err
    text = "".join(err.split())  # log records wrap at the console width, even inside paths
    assert text.count("PCDheadersaysPOINTS") == 2  # the first file's warning, then the folded line
    n_points = len(room_scans_scan_frame(seed=5, n_points=50)[0])
    first = f"{bad_headers / '0.pcd'}: PCD header says POINTS {n_points} but the data holds {n_points + 1} points"
    assert "".join(first.split()) in text
    folded = f"(fix POINTS, WIDTH and HEIGHT to use them all). ({N_FILES} files; first: {bad_headers / '0.pcd'})"
    assert "".join(folded.split()) in text
    verdict = "pa refine: verdict improved, settled after 3 rounds, ATE vs --gt 0.0302 m -> 0.0006 m"
    if quiet:
        assert err.strip().splitlines()[-1] == verdict and "quantity" not in err
    else:
        assert text.index("".join(folded.split())) < text.index("quantity")  # the warnings before the result
        assert text.count("point-to-planeRMS(m),planesfoundatthe") == 2 and verdict not in err
