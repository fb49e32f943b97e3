"""Ray casting of a spinning LiDAR through a scene (Open3D), with range noise and intensity.

Beam pattern: `beams` elevation angles evenly spaced over [-vfov/2, +vfov/2],
`azimuth_steps` columns over 360 degrees, swept counter-clockwise from azimuth 0 (the x
axis) during one scan period. Column c is fired at time c / azimuth_steps * 0.1 s after the
scan start. Points are stored column by column (all beams of column 0, then column 1, ...).
Returns closer than `min_range_m` (default 0.5 m) or farther than `max_range_m` are dropped,
like a real sensor's blind zone.

Range noise: Gaussian along the ray, sigma `range_noise_m`. For labelled hits the
noise-free range is computed in float64 from the true plane equation (not from Open3D's
float32 hit distance), so the only error of a labelled point is the range noise (plus the
float32 rounding of the PCD).

Intensity is synthetic (0..255): a fixed pseudo reflectivity per plane label times
(0.3 + 0.7 |cos incidence|); clutter 0.5. It carries no physics; it only fills the field.

Realism (off by default; `effects.py`, `vegetation.py`): rays may return from a vegetation
volume before the mesh (label -1); then, on the noise-free ranges, mixed pixels (label -1) and
dropouts; the range noise sigma may grow with the range; isotropic point noise last. Each effect
has its own random stream per scan (seed, k, stream), the range noise keeps (seed, k).

Motion distortion (off by default): when on, each column is cast from the sensor pose at
its own firing time, and the points are in the sensor frame AT THAT TIME (raw, not
deskewed), with a per-point `time` (seconds since the scan start). The ground truth pose of
a scan is the pose at the scan's start time (timestamp k * 0.1 s).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from pa_cli.runtime.open3d_preload import open3d
from pa_cli.simulate.effects import azimuth_neighbours, dropped_returns, mix_edge_returns, range_sigma_m
from pa_cli.simulate.scenes import make_scene
from pa_cli.simulate.sensor import SCAN_PERIOD_S, SensorPath, SimOptions

# The random streams of the realism effects (the range noise keeps the stream (seed, k) of before).
_STREAM_VEGETATION, _STREAM_MIXED, _STREAM_DROPOUT, _STREAM_POINT_NOISE = 1, 2, 3, 4


@dataclass
class SimScan:
    """One simulated scan. Points in the sensor frame (metres), ordered column by column."""

    points_scan: np.ndarray  # (M, 3) float64
    labels: np.ndarray  # (M,) int32 true plane label or -1
    intensity: np.ndarray  # (M,) float32, 0..255
    time: np.ndarray | None  # (M,) float64 seconds since the scan start (motion distortion only)
    T_world_sensor: np.ndarray  # (M, 4, 4) pose of each point's firing time if distorted, else (1, 4, 4)


@dataclass
class SimulatedSequence:
    """An in-memory simulated sequence (see `simulate_sequence`)."""

    scans: list[SimScan]
    T_world_scan: np.ndarray  # (N, 4, 4) ground truth, pose at each scan's start time
    timestamps: np.ndarray  # (N,) seconds, k * SCAN_PERIOD_S
    planes_world: np.ndarray  # (P, 4): n.x + d = 0, world frame
    options: SimOptions = field(default_factory=SimOptions)


class Simulator:
    """Casts the scans of one scene with one set of options (the scene is built once)."""

    def __init__(self, options: SimOptions) -> None:
        options.validate()
        o3d = open3d()
        self.scene = make_scene(options.scene, options.scene_features())
        self.options = options.resolved(self.scene)
        self.path = SensorPath(self.scene, self.options.path)
        mesh = self.scene.mesh
        self._raycaster = o3d.t.geometry.RaycastingScene()
        self._raycaster.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        self._o3d = o3d
        opt = self.options
        elevation = np.deg2rad(np.linspace(-opt.vfov_deg / 2, opt.vfov_deg / 2, opt.beams))
        azimuth = 2 * np.pi * np.arange(opt.azimuth_steps) / opt.azimuth_steps
        az, el = np.meshgrid(azimuth, elevation, indexing="ij")  # (A, B): column-major order
        self.dirs_sensor = np.column_stack([(np.cos(el) * np.cos(az)).ravel(),
                                            (np.cos(el) * np.sin(az)).ravel(), np.sin(el).ravel()])
        self.column_of_ray = np.repeat(np.arange(opt.azimuth_steps), opt.beams)
        self.beam_of_ray = np.tile(np.arange(opt.beams), opt.azimuth_steps)
        self._neighbours: np.ndarray | None = None  # azimuth neighbours, made when mixed pixels need them
        self.column_time_s = np.arange(opt.azimuth_steps) / opt.azimuth_steps * SCAN_PERIOD_S
        self.speed_mps = opt.step_m / SCAN_PERIOD_S
        # A pseudo reflectivity per plane label (0.2..1.0), clutter 0.5.
        n_labels = len(mesh.planes_world)
        self._reflectivity = np.r_[0.2 + 0.8 * np.mod(np.arange(n_labels) * 0.618034, 1.0), 0.5]

    @property
    def planes_world(self) -> np.ndarray:
        return self.scene.mesh.planes_world

    def gt_poses(self) -> np.ndarray:
        """T_world_scan (N, 4, 4): the sensor pose at each scan's start time."""
        k = np.arange(self.options.scans)
        return self.path.poses(k * self.options.step_m)

    def poses_at_times(self, time_s: np.ndarray) -> np.ndarray:
        """T_world_sensor (K, 4, 4) at times (seconds since the start of scan 0)."""
        return self.path.poses(self.speed_mps * np.asarray(time_s, dtype=np.float64))

    def scan(self, k: int) -> SimScan:
        """Cast scan k (deterministic for a given seed and k)."""
        opt = self.options
        rng = np.random.default_rng([opt.seed, k])
        t0 = k * SCAN_PERIOD_S
        if opt.motion_distortion:
            T_cols = self.poses_at_times(t0 + self.column_time_s)  # (A, 4, 4)
            T_rays = T_cols[self.column_of_ray]
            dirs_world = np.einsum("nij,nj->ni", T_rays[:, :3, :3], self.dirs_sensor)
            origins = T_rays[:, :3, 3]
        else:
            T0 = self.poses_at_times(np.array([t0]))[0]
            dirs_world = self.dirs_sensor @ T0[:3, :3].T
            origins = np.broadcast_to(T0[:3, 3], dirs_world.shape)
        rays = np.hstack([origins, dirs_world]).astype(np.float32)
        hit = self._raycaster.cast_rays(self._o3d.core.Tensor(rays), nthreads=0)
        t_hit = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy()
        finite = np.isfinite(t_hit)
        labels = np.full(len(t_hit), -1, dtype=np.int32)
        labels[finite] = self.scene.mesh.triangle_label[prim[finite]]
        # Exact float64 range for labelled hits: intersect the ray with the true plane.
        rng_m = t_hit.copy()
        lab = labels >= 0
        planes = self.planes_world[labels[lab]]
        denom = np.einsum("ij,ij->i", planes[:, :3], dirs_world[lab])
        rng_m[lab] = -(np.einsum("ij,ij->i", planes[:, :3], origins[lab]) + planes[:, 3]) / denom
        cos_incidence = np.ones(len(t_hit))
        cos_incidence[lab] = np.abs(denom)
        if self.scene.vegetation is not None:
            t_leaf = self.scene.vegetation.first_hits(
                origins, dirs_world, np.where(finite, rng_m, np.inf),
                np.random.default_rng([opt.seed, k, _STREAM_VEGETATION]),
                reach_m=opt.max_range_m + opt.step_m + 1.0)  # the sensor moves at most step_m in a scan
            leaf = np.isfinite(t_leaf)
            rng_m[leaf], labels[leaf], cos_incidence[leaf] = t_leaf[leaf], -1, 1.0
            finite |= leaf
        if opt.mixed_pixels > 0:
            valid = finite & (rng_m >= opt.min_range_m) & (rng_m <= opt.max_range_m)
            rng_m, mixed = mix_edge_returns(rng_m, valid, self._azimuth_neighbours(), opt.mixed_pixels,
                                            np.random.default_rng([opt.seed, k, _STREAM_MIXED]))
            labels[mixed], cos_incidence[mixed] = -1, 1.0
        if opt.range_noise_per_m > 0:
            noise = rng.normal(0.0, 1.0, len(t_hit)) * range_sigma_m(rng_m, opt.range_noise_m, opt.range_noise_per_m)
        elif opt.range_noise_m > 0:
            noise = rng.normal(0.0, opt.range_noise_m, len(t_hit))
        else:
            noise = np.zeros(len(t_hit))
        keep = finite & (rng_m >= opt.min_range_m) & (rng_m <= opt.max_range_m) & (rng_m + noise > 0)
        if opt.dropout > 0:
            keep &= ~dropped_returns(len(t_hit), opt.dropout, np.random.default_rng([opt.seed, k, _STREAM_DROPOUT]))
        r = rng_m[keep] + noise[keep]
        d_sensor = self.dirs_sensor[keep]
        points_scan = d_sensor * r[:, None]
        if opt.point_noise_m > 0:
            offsets = np.random.default_rng([opt.seed, k, _STREAM_POINT_NOISE]).normal(
                0.0, opt.point_noise_m, (len(t_hit), 3))
            points_scan = points_scan + offsets[keep]
        labels = labels[keep]
        refl = self._reflectivity[labels]  # label -1 picks the last entry (clutter)
        intensity = (255.0 * refl * (0.3 + 0.7 * cos_incidence[keep])).astype(np.float32)
        if opt.motion_distortion:
            time = self.column_time_s[self.column_of_ray[keep]]
            T_points = T_rays[keep]
        else:
            time = None
            T_points = T0[None]
        return SimScan(points_scan=points_scan, labels=labels, intensity=intensity, time=time,
                       T_world_sensor=T_points)

    def _azimuth_neighbours(self) -> np.ndarray:
        if self._neighbours is None or len(self._neighbours) != len(self.dirs_sensor):
            self._neighbours = azimuth_neighbours(self.column_of_ray, self.beam_of_ray, self.options.azimuth_steps)
        return self._neighbours

    def iter_scans(self) -> Iterator[SimScan]:
        for k in range(self.options.scans):
            yield self.scan(k)


def simulate_sequence(options: SimOptions) -> SimulatedSequence:
    """Simulate a whole sequence in memory (for tests and benchmarks)."""
    sim = Simulator(options)
    scans = list(sim.iter_scans())
    return SimulatedSequence(scans=scans, T_world_scan=sim.gt_poses(),
                             timestamps=np.arange(sim.options.scans) * SCAN_PERIOD_S,
                             planes_world=sim.planes_world, options=sim.options)

