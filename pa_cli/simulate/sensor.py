"""The simulated sensor: its smooth closed path through a scene and the simulation options.

The sensor follows a smooth closed path (periodic cubic spline through waypoints,
parametrised by arc length), at `step_m` metres per scan and one scan every
`SCAN_PERIOD_S` = 0.1 s, so the speed is step_m / 0.1 s. Yaw follows the path tangent;
roll and pitch are small sinusoids of the arc length. Sensor frame: x forward, y left,
z up; T_world_scan = [Rz(yaw) Ry(pitch) Rx(roll) | position]. On a shaped road (camber,
undulation) the sensor keeps its height above the road under it.

The realism options (scene features and sensor effects, `REALISM_OFF`) are all off by default
and then change nothing; `realistic` fills every one not given with `REALISTIC`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

from pa_cli.errors import UsageError
from pa_cli.simulate.scenes import SCENE_PATHS, SCENES, STREET_SCENES, Scene, SceneFeatures

SCAN_PERIOD_S = 0.1  # one sweep per 0.1 s (10 Hz), the usual spinning-LiDAR rate
BEAM_CHOICES = (16, 32, 64)
DEFAULT_VFOV_DEG = {16: 30.0, 32: 40.0, 64: 45.0}  # VLP-16 +-15, HDL-32-like, OS1-64 +-22.5
# The realism options off (the default: a sequence exactly as without them) and `--realistic`.
SCENE_FEATURE_KEYS = tuple(f.name for f in fields(SceneFeatures))
REALISM_OFF: dict[str, float | bool] = {**{f.name: f.default for f in fields(SceneFeatures)},
                                        "range_noise_per_m": 0.0, "point_noise_m": 0.0,
                                        "mixed_pixels": 0.0, "dropout": 0.0}
REALISTIC: dict[str, float | bool] = {
    "vegetation": 0.4,  # trees and hedges along 40 % of the street
    "curved_cars": True,
    "road_camber_m": 0.1,  # 10 cm from the crown to the kerb
    "road_undulation_m": 0.03,  # a 3 cm swell every 30 m
    "facade_relief": True,
    "facade_gaps": False,  # a property of the street, not of the sensor: the avenue has them
    "range_noise_per_m": 0.001,  # with the default 1 cm: 1 cm + 0.1 % of the range
    "point_noise_m": 0.0,
    "mixed_pixels": 0.02,
    "dropout": 0.05,
}


class SensorPath:
    """A smooth closed path: position, yaw along the tangent, small roll/pitch, by arc length."""

    _SAMPLES = 20000

    def __init__(self, scene: Scene, path: str | None = None) -> None:
        from scipy.interpolate import CubicSpline

        waypoints_xy = scene.paths[next(iter(scene.paths)) if path is None else path]
        pts = np.vstack([waypoints_xy, waypoints_xy[:1]])
        chord = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))]
        self._spline = CubicSpline(chord, pts, bc_type="periodic")
        u = np.linspace(0.0, chord[-1], self._SAMPLES + 1)
        speed = np.linalg.norm(self._spline(u, 1), axis=1)
        length = np.r_[0.0, np.cumsum((speed[1:] + speed[:-1]) / 2 * np.diff(u))]
        self._u, self._s = u, length
        self.length_m = float(length[-1])
        self.height_m = scene.sensor_height_m
        self.roll_amp_rad = np.deg2rad(scene.roll_amplitude_deg)
        self.pitch_amp_rad = np.deg2rad(scene.pitch_amplitude_deg)
        self.roll_period_m = scene.roll_period_m
        self.pitch_period_m = scene.pitch_period_m
        self.ground_height = scene.ground_height

    def poses(self, s_m: np.ndarray) -> np.ndarray:
        """T_world_sensor (K, 4, 4) at arc lengths `s_m` (metres, wrapped around the loop)."""
        s = np.mod(np.asarray(s_m, dtype=np.float64), self.length_m)
        u = np.interp(s, self._s, self._u)
        xy = self._spline(u)
        dxy = self._spline(u, 1)
        yaw = np.arctan2(dxy[:, 1], dxy[:, 0])
        roll = self.roll_amp_rad * np.sin(2 * np.pi * s / self.roll_period_m)
        pitch = self.pitch_amp_rad * np.sin(2 * np.pi * s / self.pitch_period_m + 0.5)
        cy, sy = np.cos(yaw), np.sin(yaw)
        cp, sp = np.cos(pitch), np.sin(pitch)
        cr, sr = np.cos(roll), np.sin(roll)
        T = np.zeros((len(s), 4, 4))
        # R = Rz(yaw) Ry(pitch) Rx(roll)
        T[:, 0, 0] = cy * cp
        T[:, 0, 1] = cy * sp * sr - sy * cr
        T[:, 0, 2] = cy * sp * cr + sy * sr
        T[:, 1, 0] = sy * cp
        T[:, 1, 1] = sy * sp * sr + cy * cr
        T[:, 1, 2] = sy * sp * cr - cy * sr
        T[:, 2, 0] = -sp
        T[:, 2, 1] = cp * sr
        T[:, 2, 2] = cp * cr
        T[:, 0, 3] = xy[:, 0]
        T[:, 1, 3] = xy[:, 1]
        T[:, 2, 3] = self.height_m
        if self.ground_height is not None:
            T[:, 2, 3] += self.ground_height(xy[:, 0], xy[:, 1])
        T[:, 3, 3] = 1.0
        return T



@dataclass
class SimOptions:
    """Options of a simulation; None means the scene's or beam count's default."""

    scene: str = "office"
    path: str | None = None  # a name from the scene's paths; None: its first (default) path
    scans: int = 50
    step_m: float | None = None
    beams: int = 16
    vfov_deg: float | None = None
    azimuth_steps: int = 1024
    range_noise_m: float = 0.01
    max_range_m: float | None = None
    min_range_m: float = 0.5
    seed: int = 0
    motion_distortion: bool = False
    # Realism (None: off, or the `REALISTIC` value with `realistic`); see `REALISM_OFF`.
    realistic: bool = False
    vegetation: float | None = None  # share of the street's length with trees and hedges, 0..1
    curved_cars: bool | None = None
    road_camber_m: float | None = None  # drop from the road's crown to the kerb (m)
    road_undulation_m: float | None = None  # amplitude of the swell along the road (m)
    facade_relief: bool | None = None
    facade_gaps: bool | None = None
    range_noise_per_m: float | None = None  # range noise sigma grows by this per metre of range
    point_noise_m: float | None = None  # isotropic 3D Gaussian noise per point, sigma (m)
    mixed_pixels: float | None = None  # share of all returns moved between the surfaces of a depth edge
    dropout: float | None = None  # share of returns missing at random

    def validate(self) -> None:
        """Raise `UsageError` (exit 2) naming the flag of the first bad value."""
        if self.scene not in SCENES:
            raise UsageError(f"unknown scene '{self.scene}'; choose one of {', '.join(SCENES)}.")
        if self.path is not None and self.path not in SCENE_PATHS[self.scene]:
            raise UsageError(f"--path {self.path} is not a path of scene '{self.scene}'; choose one of "
                             f"{', '.join(SCENE_PATHS[self.scene])}.")
        if self.beams not in BEAM_CHOICES:
            raise UsageError(f"--beams must be one of 16, 32, 64; got {self.beams}.")
        checks = [("--scans", self.scans, 1), ("--azimuth-steps", self.azimuth_steps, 8)]
        for flag, value, least in checks:
            if value < least:
                raise UsageError(f"{flag} must be at least {least}; got {value}.")
        positive = [("--step-m", self.step_m), ("--vfov-deg", self.vfov_deg),
                    ("--max-range-m", self.max_range_m)]
        for flag, value in positive:
            if value is not None and not (np.isfinite(value) and value > 0):
                raise UsageError(f"{flag} must be a positive number; got {value}.")
        for flag, value in (("--range-noise-m", self.range_noise_m), ("--min-range-m", self.min_range_m)):
            if not (np.isfinite(value) and value >= 0):
                raise UsageError(f"{flag} must be zero or positive; got {value}.")
        if self.vfov_deg is not None and self.vfov_deg >= 180:
            raise UsageError(f"--vfov-deg must be below 180; got {self.vfov_deg}.")
        if self.max_range_m is not None and self.max_range_m <= self.min_range_m:
            raise UsageError(f"--max-range-m ({self.max_range_m}) must exceed --min-range-m "
                             f"({self.min_range_m}).")
        if self.seed < 0:
            raise UsageError(f"--seed must be zero or positive; got {self.seed}.")
        bounded = [("--vegetation", self.vegetation, 1.0), ("--road-camber-m", self.road_camber_m, 1.0),
                   ("--road-undulation-m", self.road_undulation_m, 0.3),
                   ("--range-noise-per-m", self.range_noise_per_m, 0.1), ("--point-noise-m", self.point_noise_m, 1.0),
                   ("--mixed-pixels", self.mixed_pixels, 1.0), ("--dropout", self.dropout, 0.99)]
        for flag, value, most in bounded:
            if value is not None and not (np.isfinite(value) and 0 <= value <= most):
                raise UsageError(f"{flag} must be between 0 and {most}; got {value}.")
        if self.scene not in STREET_SCENES:
            given = [key for key in SCENE_FEATURE_KEYS if getattr(self, key) not in (None, REALISM_OFF[key])]
            if given:
                raise UsageError(f"--{given[0].replace('_', '-')} applies to the street scenes "
                                 f"({', '.join(STREET_SCENES)}); scene '{self.scene}' has no street.")

    def with_realism(self) -> SimOptions:
        """A copy with every realism option set: given, else `REALISTIC` (with `realistic`; scene
        features only on the street scenes), else off."""
        out = SimOptions(**asdict(self))
        for key, off in REALISM_OFF.items():
            if getattr(self, key) is None:
                use_preset = self.realistic and (key not in SCENE_FEATURE_KEYS or self.scene in STREET_SCENES)
                setattr(out, key, REALISTIC[key] if use_preset else off)
        return out

    def scene_features(self) -> SceneFeatures:
        """The scene features of these options (unset ones off)."""
        realism = self.with_realism()
        return SceneFeatures(**{key: getattr(realism, key) for key in SCENE_FEATURE_KEYS})

    def record(self) -> dict:
        """The options as written to meta.json; without any realism, exactly the keys of before."""
        out = asdict(self)
        if not self.realistic and all(out[key] in (None, off) for key, off in REALISM_OFF.items()):
            for key in ("realistic", *REALISM_OFF):
                del out[key]
        return out

    def resolved(self, scene: Scene) -> SimOptions:
        """A copy with every None replaced by its default."""
        out = self.with_realism()
        out.path = next(iter(scene.paths)) if self.path is None else self.path
        out.step_m = scene.default_step_m if self.step_m is None else self.step_m
        out.vfov_deg = DEFAULT_VFOV_DEG[self.beams] if self.vfov_deg is None else self.vfov_deg
        out.max_range_m = scene.default_max_range_m if self.max_range_m is None else self.max_range_m
        return out


def in_horizontal_fov(dirs_sensor: np.ndarray, hfov_deg: float) -> np.ndarray:
    """(M,) mask of the beam directions (M, 3) (sensor frame) within a horizontal field of view of
    `hfov_deg` degrees centred on the sensor's x axis (360: every direction)."""
    azimuth = np.arctan2(dirs_sensor[:, 1], dirs_sensor[:, 0])
    return np.abs(azimuth) <= np.deg2rad(hfov_deg) / 2
