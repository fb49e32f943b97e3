"""`pa refine --resume`: a run stopped after a round (Ctrl-C, or killed with SIGKILL) and resumed
gives the poses of an uninterrupted run; the work folder is refused without --resume, for other
inputs, and removed on success; the memory checks warn before each stage above the budget."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

N_ROUNDS = 7
KILL_TIMEOUT_S = 600.0  # the subprocess's first round file must appear by then (a loaded CI machine)


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> tuple[Path, Path]:
    """A small office sequence with per-point times, and a config whose rounds run to the cap:
    four fresh associations, then frozen rounds with the deskew fixed point's extrapolation (the initial
    trajectory's motions as the odometry factors' measurements: their loose sigmas leave the deskew fixed
    point a slow contraction for the extrapolation, and its memory, to act on)."""
    from pa_cli.cli import run
    from pa_cli.config import dump_config, load_config

    root = tmp_path_factory.mktemp("resume")
    assert run(["simulate", "office", str(root / "seq"), "--scans", "24", "--azimuth-steps", "180",
                "--motion-distortion", "--seed", "2"]) == 0
    config = load_config("indoor")
    config.refine.max_rounds = N_ROUNDS
    config.advanced.association.rounds = 4  # fresh associations, whether or not the rounds' moves settle them
    config.advanced.odometry.measurements = "initial"
    config.refine.pose_change_tolerance_m, config.refine.pose_change_tolerance_deg = 1e-6, 1e-5
    (root / "cfg.yaml").write_text(dump_config(config))
    return root / "seq" / "scans", root / "cfg.yaml"


def _reference(run_pa, work: Path, tmp_path: Path, scans: Path, cfg: Path) -> Path:
    """The uninterrupted rounds from the same finished stages as the stopped run: its work folder
    without the round file (KISS-ICP's threads make two fresh runs differ in the last bits, which
    the registered motions and the association amplify), resumed in another folder."""
    out = tmp_path / "reference" / "m.ply"
    shutil.copytree(work, out.with_name("m.work"), ignore=shutil.ignore_patterns("round.npz"))
    code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q", "--resume")
    assert code == 0, err
    report = json.loads(out.with_name("m_report.json").read_text())
    assert [r["association"] for r in report["rounds"]] == ["new"] * 4 + ["frozen"] * 3
    assert any((r.get("deskew_acceleration") or {}).get("extrapolated") for r in report["rounds"])
    assert not out.with_name("m.work").exists()  # removed on success
    return out


def _same_result(out: Path, reference: Path) -> None:
    """The same poses (KITTI text, 9 decimals) and the same rounds."""
    resumed, uninterrupted = (json.loads(p.with_name("m_report.json").read_text()) for p in (out, reference))
    np.testing.assert_allclose(np.loadtxt(out.with_name("m_poses_kitti.txt")),
                               np.loadtxt(reference.with_name("m_poses_kitti.txt")), rtol=0, atol=1.5e-9)
    assert [r["max_pose_change_m"] for r in resumed["rounds"]] == \
        [r["max_pose_change_m"] for r in uninterrupted["rounds"]]
    assert resumed["quality"]["verdict"] == uninterrupted["quality"]["verdict"]


@pytest.mark.parametrize("stop_after_round", [1, 5])
def test_ctrl_c_after_a_round_then_resume_gives_the_uninterrupted_poses(
        run_pa, monkeypatch, tmp_path, sequence, stop_after_round):
    """Ctrl-C right after round k's carry is kept (k = 1: a fresh association; k = 5: a frozen
    round whose successor extrapolates the deskew fixed point): exit 130, the work folder kept
    with a line naming --resume; the same command with --resume gives the poses of the rounds
    run without a stop."""
    from pa_cli.refine.work import WorkFolder

    scans, cfg = sequence
    out = tmp_path / "m.ply"
    save_carry = WorkFolder.save_carry

    def save_then_stop(self, carry):
        save_carry(self, carry)
        if carry.next_round == stop_after_round:
            raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(WorkFolder, "save_carry", save_then_stop)
        code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q")
    assert code == 130
    assert "--resume" in err and (tmp_path / "m.work" / "round.npz").exists() and not out.exists()
    reference = _reference(run_pa, tmp_path / "m.work", tmp_path, scans, cfg)

    code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q")
    assert code == 1 and "--resume" in err and "--force" in err  # the work folder is not silently reused

    code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q", "--resume")
    assert code == 0, err
    _same_result(out, reference)
    assert not (tmp_path / "m.work").exists()


def test_sigkill_in_the_rounds_then_resume_gives_the_uninterrupted_poses(run_pa, tmp_path, sequence):
    """A `pa refine` subprocess killed with SIGKILL once its first round file appears; --resume
    continues from it and gives the poses of the rounds run without a stop."""
    scans, cfg = sequence
    out = tmp_path / "m.ply"
    command = [sys.executable, "-m", "pa_cli", "refine", str(scans), "--out", str(out), "--config", str(cfg), "-q"]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    round_file = tmp_path / "m.work" / "round.npz"
    deadline = time.monotonic() + KILL_TIMEOUT_S
    while not round_file.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    os.kill(process.pid, signal.SIGKILL)
    process.wait()
    assert round_file.exists() and not out.exists(), "the subprocess was not killed in its rounds"
    reference = _reference(run_pa, tmp_path / "m.work", tmp_path, scans, cfg)

    code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q", "--resume", "--keep-work")
    assert code == 0, err
    _same_result(out, reference)
    assert (tmp_path / "m.work" / "manifest.json").exists()  # --keep-work


def test_resume_refuses_a_work_folder_of_another_config(run_pa, tmp_path, sequence):
    """A work folder made with one config is refused by --resume with another (naming what
    differs and the fix); --force without --resume starts over."""
    scans, cfg = sequence
    out = tmp_path / "m.ply"
    work = tmp_path / "m.work"
    work.mkdir()
    (work / "manifest.json").write_text(json.dumps({"config_digest": "another", "n_scans": 24}))
    code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q", "--resume", "--rounds", "1")
    err = " ".join(err.split())
    assert code == 1 and "other inputs" in err and "the config" in err and "--force" in err and not out.exists()
    code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q", "--force", "--rounds", "1")
    assert code == 0, err
    assert out.exists() and not work.exists()


def test_memory_checks_warn_before_each_stage_above_the_budget(run_pa, tmp_path, sequence):
    """With a tiny execution.memory_budget_gb every stage over the sequence warns, naming itself,
    its estimate and the key; the run still completes (the covariance skips itself)."""
    from pa_cli.config import dump_config, load_config

    scans, cfg = sequence
    config = load_config(str(cfg))
    config.execution.memory_budget_gb = 1e-7
    tiny = tmp_path / "tiny.yaml"
    tiny.write_text(dump_config(config))
    out = tmp_path / "m.ply"
    code, _, err = run_pa("refine", scans, "--out", out, "--config", tiny, "--rounds", "1", "--loops")
    err = " ".join(err.split())
    assert code == 0, err
    for stage in ("odometry", "loops", "planes", "adjust 1", "map"):
        assert f"{stage}: expected to hold about" in err, stage
    assert err.count("above execution.memory_budget_gb = 1e-07") >= 5


def test_a_known_failure_leaves_no_work_folder(run_pa, monkeypatch, tmp_path, sequence):
    """A `PaError` in a stage (here the rounds finding no planes) exits 1 and removes the work
    folder with the stages it had kept: resuming would only meet the same failure."""
    from pa_cli.errors import SolverError

    def no_planes(*args, **kwargs):
        raise SolverError("no plane seen by two scans")

    scans, cfg = sequence
    out = tmp_path / "m.ply"
    monkeypatch.setattr("pa_cli.refine.pipeline.refine_rounds", no_planes)
    code, _, err = run_pa("refine", scans, "--out", out, "--config", cfg, "-q")
    assert code == 1 and "no plane seen by two scans" in err
    assert list(tmp_path.iterdir()) == []
