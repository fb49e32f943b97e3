"""Simulated rig calibration cases shared by tests/e2e/test_calibration.py and bench/calibration.py.

A case is a rig file (LiDAR mountings, beams, fields of view) in the office scene; `run_case`
simulates it (`pa simulate --rig`), writes an --init file whose every extrinsic is the true one
turned by `init_deg` about a random axis and moved `init_m` in a random direction, runs
`pa calibrate` and returns the rotation (deg) and translation (m) errors of every extrinsic and the
directions it reported unobservable.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from pa_cli.core.geometry import exp_so3, rotation_angles
from pa_cli.io.extrinsics import read_extrinsics, write_extrinsics


@dataclass(frozen=True)
class RigCase:
    name: str
    lidars: tuple[dict, ...]


OVERLAP_2x16 = RigCase("2 lidars, overlapping, 16 beams", (
    {"xyz_m": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0], "beams": 16},
    {"xyz_m": [0.3, -0.4, 0.2], "rpy_deg": [2.0, 10.0, -30.0], "beams": 16},
))
BARELY_2x16 = RigCase("2 lidars, barely overlapping (120 deg each, 20 deg shared), 16 beams", (
    {"xyz_m": [0.2, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0], "beams": 16, "hfov_deg": 120.0},
    {"xyz_m": [-0.2, -0.3, 0.1], "rpy_deg": [0.0, 5.0, -100.0], "beams": 16, "hfov_deg": 120.0},
))
OVERLAP_2x32 = RigCase("2 lidars, overlapping, 32 beams", (
    {"xyz_m": [0.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0], "beams": 32},
    {"xyz_m": [-0.25, 0.35, 0.15], "rpy_deg": [-3.0, 15.0, 45.0], "beams": 32},
))
THREE_MIXED = RigCase("3 lidars, 16 + 32 + 16 beams, side units barely overlapping", (
    {"xyz_m": [0.0, 0.0, 0.3], "rpy_deg": [0.0, 0.0, 0.0], "beams": 32},
    {"xyz_m": [0.1, 0.5, 0.0], "rpy_deg": [0.0, 10.0, 90.0], "beams": 16, "hfov_deg": 180.0},
    {"xyz_m": [0.1, -0.5, 0.0], "rpy_deg": [0.0, 10.0, -90.0], "beams": 16, "hfov_deg": 180.0},
))
CASES = (OVERLAP_2x16, BARELY_2x16, OVERLAP_2x32, THREE_MIXED)


def perturbed_extrinsics(T_base_lidar: np.ndarray, angle_deg: float, shift_m: float, seed: int) -> np.ndarray:
    """Every extrinsic but lidar0's turned by `angle_deg` about a random axis (about its own origin)
    and moved `shift_m` in a random direction."""
    rng = np.random.default_rng(seed)
    out = np.array(T_base_lidar, dtype=np.float64)
    for k in range(1, len(out)):
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        out[k, :3, :3] = exp_so3((np.deg2rad(angle_deg) * axis / np.linalg.norm(axis))[None])[0] @ out[k, :3, :3]
        out[k, :3, 3] += shift_m * shift / np.linalg.norm(shift)
    return out


def extrinsic_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (deg) and translation (m) errors of every extrinsic but lidar0's."""
    R_err = np.einsum("kji,kjl->kil", T_est[1:, :3, :3], T_true[1:, :3, :3])
    return np.rad2deg(rotation_angles(R_err)), np.linalg.norm(T_est[1:, :3, 3] - T_true[1:, :3, 3], axis=1)


def run_case(run_pa, work: Path, case: RigCase, seed: int, scans: int, azimuth_steps: int,
             init_deg: float = 5.0, init_m: float = 0.2, scene: str = "office", step_m: float = 0.2,
             config: str = "indoor") -> dict:
    """Simulate `scene`, perturb, calibrate with the preset `config`; returns the errors and the CPU
    and wall times (s) of `pa calibrate` (CPU time of this process: pass an in-process `run_pa`)."""
    rig_file = work / "rig.yaml"
    rig_file.write_text(yaml.safe_dump({"lidars": [dict(lidar) for lidar in case.lidars]}))
    code, _, err = run_pa("simulate", "office", str(work / "rig"), "--rig", str(rig_file), "--scans", str(scans),
                          "--azimuth-steps", str(azimuth_steps), "--step-m", str(step_m), "--seed", str(seed))
    assert code == 0, err
    T_true = read_extrinsics(work / "rig" / "gt_extrinsics.yaml")
    write_extrinsics(work / "init.yaml", perturbed_extrinsics(T_true, init_deg, init_m, seed))
    wall, cpu = time.perf_counter(), time.process_time()
    code, _, err = run_pa("calibrate", str(work / "rig"), "--out", str(work / "extrinsics.yaml"), "--init",
                          str(work / "init.yaml"), "--config", config, "--quiet")
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    assert code == 0, err
    rot_deg, trans_m = extrinsic_errors(read_extrinsics(work / "extrinsics.yaml"), T_true)
    written = yaml.safe_load((work / "extrinsics.yaml").read_text())["lidars"]
    unobservable = [w for entry in written.values() for w in entry.get("unobservable", [])]
    init_rot_deg, init_trans_m = extrinsic_errors(read_extrinsics(work / "init.yaml"), T_true)
    return {"rotation_error_deg": rot_deg, "translation_error_m": trans_m, "init_rotation_error_deg": init_rot_deg,
            "init_translation_error_m": init_trans_m, "unobservable": unobservable, "wall_s": wall, "cpu_s": cpu}
