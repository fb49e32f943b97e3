"""The config model: a few user-facing sections, then `advanced`.

The user-facing sections (`sensor`, `scene`, `refine`, `loops`, `map`, `execution`) hold the keys a
user is expected to set, each with its unit in its name and a docstring that says when to change
it. `advanced` holds every other tunable, in one subsection per part of the program; its keys are
listed in docs/config.md. A key's docstring is its description in `pa config show`, in every
dumped config (`pa_cli.config.load.dump_config`) and in docs/config.md.

`PlanesConfig` is not a section of the file: it is what the plane code takes, `advanced.planes`
with the scene's plane voxel and thickness and `execution.threads` (`PaConfig.planes_config()`).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, use_attribute_docstrings=True)


# ------------------------------------------------------------------------------------------------ user-facing


class SensorConfig(_Section):
    """The LiDAR: which points to keep and whether to motion-compensate them."""

    min_range_m: float = Field(0.5, ge=0)
    """Drop points closer than this (m). Raise it to cut away the vehicle, the robot or the person carrying the
    sensor (outdoor preset: 2 m)."""
    max_range_m: float = Field(100.0, gt=0)
    """Drop points farther than this (m). Lower it to the sensor's useful range indoors (indoor preset: 30 m), where far
    returns are noise or reflections."""
    deskew: Literal["auto", "on", "off"] = Field("auto")
    """Motion compensation with per-point times (fields time, t, timestamp, offset_time): every point is moved to its
    scan's reference instant with the current trajectory, every round. auto: on when the scans have a time field;
    on: required (error without one); off when the time field is wrong or the scans are already deskewed.
    """


class SceneConfig(_Section):
    """What the sensor sees: the size of the planes and whether poles and posts help."""

    plane_voxel_m: float = Field(1.0, gt=0)
    """Edge of the voxel grid planes are found in (m; `pa refine` fixes the grid to the held scan's pose at the start
    of its rounds); large enough to hold a plane patch, small enough to avoid corners. Outdoors (facades, ground) 1 m;
    indoors (rooms, corridors) 0.5 m (indoor preset)."""
    max_plane_thickness_m: float = Field(0.05, gt=0)
    """A voxel's points, and a merged plane, count as planar when their RMS point-to-plane distance is below this (m):
    about 3x the sensor noise plus the initial pose error. Raise it for a noisy sensor or rough surfaces when too few
    planes are found."""
    edges: bool | Literal["auto"] = Field("auto")
    """Find edges (poles, posts, frames) and adjust them with the planes (true, false or auto). auto: where the
    first round's planes leave some scan poorly constrained (`advanced.planes.min_constraint_eigenvalue`), edges are
    found and kept for the whole run when they leave fewer such scans (sparse outdoor scans, where the planes leave
    the direction of travel free and poles hold it); where the planes hold every scan they add nothing and are not
    looked for."""

    @field_validator("edges", mode="before")
    @classmethod
    def _edges_switch(cls, value: object) -> object:
        """true, false or auto, with one message for anything else (not one per alternative)."""
        if value is True or value is False or value == "auto":
            return value
        raise ValueError("Input should be true, false or auto")


class RefineConfig(_Section):
    """The rounds of `pa refine` and how far the odometry is trusted."""

    max_rounds: int = Field(15, ge=1)
    """Rounds (association + adjustment) at most; the loop stops earlier when no pose moves more than the tolerances
    (settled), and the report says whether it did. Raise it when the report says the rounds did not settle.
    """
    pose_change_tolerance_m: float = Field(1e-3, gt=0)
    """Settled when no pose moves more in a round (m). Lower it when millimetres matter more than run time."""
    pose_change_tolerance_deg: float = Field(0.01, gt=0)
    """Settled when no pose turns more in a round (deg)."""
    odometry_translation_sigma_m: float | None = Field(0.05, gt=0)
    """Odometry factors between consecutive scans: translation 1-sigma of the initial trajectory's relative motion at
    standstill (m), for the pairs whose factor keeps that motion (a pair that did not register, or
    advanced.odometry.measurements: initial; registered pairs take the registrations' noise measured on the scans,
    `motion_noise` in the report) and for the size of a break the verdict looks for; null: no factors (directions
    the planes leave free are then unconstrained). Lower it for initial poses better than LiDAR odometry (GNSS/INS
    through --poses), raise it for a poor odometry.
    """
    odometry_rotation_sigma_deg: float = Field(0.5, gt=0)
    """Odometry factors: rotation 1-sigma of the initial trajectory's relative motion at standstill (deg), where
    refine.odometry_translation_sigma_m's applies; sparse 16-beam scans give scan-to-map rotations good to a few
    tenths of a degree. Lower it with an IMU-backed odometry.
    """


class LoopsConfig(_Section):
    """Loop closure between the odometry and the rounds: candidates, verification, pose graph."""

    enabled: bool = Field(True)
    """Close loops before the rounds (`--loops`/`--no-loops` override it): a sequence that revisits places after a long
    path gets its odometry drift corrected. A path shorter than min_separation_m reads nothing and costs nothing; a
    longer one without revisits pays for the local maps and the candidates it rejects (docs/loops.md). Turn it off
    (`--no-loops`) to keep the odometry's trajectory as the start whatever the scans show.
    """
    min_separation_m: float = Field(50.0, gt=0)
    """Odometry path length between two places for them to be a loop candidate (m); nearer ones are consecutive, not
    loops. Lower it when the sequence closes loops around a block shorter than this.
    """


class MapConfig(_Section):
    """The merged map written next to the poses."""

    voxel_m: float = Field(0.1, ge=0)
    """Voxel size of the written map (m): one point per voxel; 0 keeps every point. Smaller keeps more detail and a
    larger file (indoor preset: 5 cm, outdoor: 20 cm); `pa refine --map-voxel-m` overrides it."""


class ExecutionConfig(_Section):
    """Where the work runs and how much memory and how many cores it may take."""

    threads: int = Field(2, ge=1)
    """Threads of this process for plane detection, association and the loop stage's local maps (the kernels release
    the GIL, so up to one per core helps), and processes of this machine for the GICP registrations, which hold the
    GIL (consecutive pairs of scan files from 200 scans on, loop candidates from 80). Raise it to the cores you can
    spare."""
    memory_budget_gb: float = Field(8.0, gt=0)
    """Peak memory the work may plan for (GB): the hierarchical backend bounds the windows in flight and skips its flat
    final pass above it, the pose covariance is skipped above it, a local dask cluster's workers share it. Set it to
    the memory you can spare.
    """
    cache_budget_gb: float = Field(4.0, gt=0)
    """The point cache holds at most this much (GB); scans read after it is full are re-read when needed, so a long
    sequence runs in bounded memory (keep it below memory_budget_gb).
    """
    workers: int = Field(0, ge=0)
    """Worker processes of a local dask cluster for the windows (0: run them in this process, one after another).
    Use for long sequences (thousands of scans) on a machine with cores to spare."""
    scheduler_address: str | None = Field(None)
    """Address tcp://HOST:PORT of a running dask scheduler to use instead of a local cluster (its workers must have pa
    installed and see the scan files).
    """
    threads_per_worker: int = Field(1, ge=1)
    """Threads per local worker process; 1 keeps numpy and numba from oversubscribing the cores the processes already
    use. Raise it only with fewer workers than cores.
    """


# ------------------------------------------------------------------------------------------------ advanced


class KissIcpConfig(_Section):
    """KISS-ICP initial poses (used when `--poses` is not given)."""

    voxel_size_m: float | None = Field(None, gt=0)
    """KISS-ICP map voxel (m); null: sensor.max_range_m / 100."""
    deskew: bool = Field(False)
    """Let KISS-ICP motion-compensate scans with per-point times (needs a time field)."""


class OdometryConfig(_Section):
    """Odometry factors: how the trust in a relative motion grows with it, and its weight against the planes."""

    point_sigma_m: float = Field(0.1, gt=0)
    """Effective point-to-plane sigma (m) that scales the odometry factors into the plane cost's m^2 where the
    motions' noise is not measured (measurements: initial, or too few pairs registered to measure it); otherwise
    each round measures it from the planes' residuals (`rounds[].balance_point_sigma_m` in the report). Larger than
    the range noise: the cost counts every point as independent, but the points of one scan on one plane share
    their errors (deskew, beam calibration, surface roughness), so thousands of points carry far less information
    than their count says.
    """
    translation_sigma_per_m: float = Field(0.02, ge=0)
    """Translation sigma added to refine.odometry_translation_sigma_m per metre travelled between the two scans (m/m;
    LiDAR odometry drifts about 1 %, more on sparse or distorted scans).
    """
    rotation_sigma_per_deg: float = Field(0.05, ge=0)
    """Rotation sigma added to refine.odometry_rotation_sigma_deg per degree turned between the two scans (deg/deg)."""
    rotation_sigma_deg_per_m: float = Field(0.02, ge=0)
    """Rotation sigma added per metre travelled (deg/m)."""
    measurements: Literal["initial", "registration"] = Field("registration")
    """What the odometry factors measure: the initial trajectory's relative motions, or each consecutive pair
    registered on its scans (GICP on all points, iterated to its own fixed point from the initial motion, with the
    registrations' noise per axis measured on closures of three scans; a pair that does not converge keeps the
    initial motion and the sigmas above), so the answer does not follow the start where the planes are weak.
    """


class AdvancedPlanesConfig(_Section):
    """Plane detection by voxel region growing and association across scans (besides scene.plane_voxel_m and
    scene.max_plane_thickness_m)."""

    max_subdivision_levels: int = Field(2, ge=0, le=3)
    """Octree splits of non-planar voxels (BALM2-style), to recover planes next to corners and clutter."""
    min_points: int = Field(10, ge=4)
    """Points (all scans together) a voxel needs to be tested for planarity; fewer give unreliable normals."""
    max_eigen_ratio: float = Field(0.05, gt=0)
    """Planar if lambda_min / lambda_mid of the point covariance is below this (rejects lines and blobs)."""
    max_normal_angle_deg: float = Field(10.0, gt=0, le=90)
    """Merge adjacent voxels whose normals differ at most this much (deg)."""
    max_plane_distance_m: float = Field(0.05, gt=0)
    """Merge adjacent voxels whose centroids lie at most this far from each other's plane (m); below the smallest step
    between parallel surfaces to keep apart (facade setbacks).
    """
    neighbourhood: Literal[6, 26] = Field(26)
    """Voxels adjacent for region growing: 6 (share a face) or 26 (touch); 26 keeps planes oblique to the grid in one
    piece where the plane only clips a voxel.
    """
    max_split_rounds: int = Field(100, ge=0)
    """Rounds of re-seeding a merged region that is not planar, or a landmark that is not flat at its noise level
    (each round keeps the part that agrees with its largest voxel); voxels left after the last round are dropped. A
    cambered, undulating road of a few hundred metres splits into a few dozen parts.
    """
    leaf_outlier_sigma: float = Field(2.0, gt=0)
    """Drop a voxel from its landmark when its RMS distance to the landmark plane exceeds this many robust sigmas;
    voxels at corners otherwise tilt small planes.
    """
    leaf_refit_rounds: int = Field(3, ge=0)
    """Rounds of dropping off-plane voxels and refitting the landmark planes."""
    grow_into_sparse: bool = Field(True)
    """Extend each landmark over adjacent voxels with fewer than min_points points whose points fit its plane (RMS
    distance within leaf_outlier_sigma sigmas), ring by ring with a refit after each ring: far, sparsely sampled
    facades and narrow surfaces split over small voxels are otherwise lost.
    """
    min_points_per_observation: int = Field(10, ge=3)
    """Points one scan needs on a landmark to observe it; fewer give a weak constraint."""
    outlier_sigma: float = Field(3.0, gt=0)
    """Trim points farther than this many sigmas (the landmark's RMS thickness) from the landmark plane."""
    outlier_sigma_floor_m: float = Field(0.002, gt=0)
    """Lower bound on the sigma used for trimming (m), so noise-free or very thin landmarks do not lose points to
    rounding.
    """
    max_normal_uncertainty_deg: float = Field(1.0, gt=0)
    """After association, drop a landmark whose normal, refit on its kept points, has a standard deviation above this
    (deg; indoors 0.25): narrow strips (door frames, wall ends) are dominated by junction points and constrain the
    poses weakly.
    """
    refit_min_kept_fraction: float = Field(0.75, ge=0, le=1)
    """After association, a landmark whose kept points are under half as thick as its detection sigma (a plane tilted
    by junction leaves) is refit on its kept points and re-trimmed when they are at least this fraction of its
    detected points; else it is dropped (a minority subset does not define the landmark's plane).
    """
    tilted_thickness_fraction: float = Field(0.5, gt=0, le=1)
    """After association, a landmark whose kept points' RMS thickness is below this fraction of its detection sigma
    (unitless) was detected on a tilted plane: trimming removed the junction points that tilted it.
    """
    side_grazing_angle_deg: float = Field(10.0, gt=0, lt=90)
    """An observation whose mean ray meets its landmark plane at less than this angle (deg) has no side
    (`pa_cli.planes.sides`): a landmark seen from both sides of its plane is two surfaces (the faces of a wall) and is
    split; below this angle the sign of the side is decided by the errors of the normal and of the scan's rotation (an
    initial pose a few degrees off) and by the surface's bends (ground far away is seen at a few degrees), not by the
    geometry, so such observations of a two-sided landmark are dropped.
    """
    min_constraint_eigenvalue: float = Field(0.1, ge=0)
    """A scan is reported poorly constrained when the smallest eigenvalue of the sum of n n^T over its landmark normals
    is below this (unitless; 1 = one plane square to the weakest direction).
    """


class PlanesConfig(AdvancedPlanesConfig):
    """What the plane code takes (`PaConfig.planes_config()`): `advanced.planes` with the scene's plane voxel and
    thickness and `execution.threads`. Not a section of the file; its defaults are those of the keys it copies."""

    voxel_size_m: float = Field(SceneConfig.model_fields["plane_voxel_m"].default, gt=0)
    """scene.plane_voxel_m (m)."""
    max_thickness_m: float = Field(SceneConfig.model_fields["max_plane_thickness_m"].default, gt=0)
    """scene.max_plane_thickness_m (m); also applied to each merged landmark."""
    association_threads: int = Field(ExecutionConfig.model_fields["threads"].default, ge=1)
    """execution.threads: scans summed (plane detection) and associated at once."""


class EdgesConfig(_Section):
    """Edge (line) detection when scene.edges is on: poles, posts and frames, as line landmarks for the adjustment.

    A line's cost is the sum of squared point-to-line distances (lambda_min + lambda_mid of its
    points); lines constrain the directions planes leave free (along a street of parallel facades).
    """

    voxel_size_m: float = Field(1.0, gt=0)
    """Edge of the world-frame voxel grid for line detection (m); about the length of line a voxel must hold."""
    min_points: int = Field(8, ge=3)
    """Points (all scans together) a voxel needs to be tested for a line; fewer give unreliable directions."""
    max_mid_ratio: float = Field(0.05, gt=0)
    """Line-like if lambda_mid / lambda_max of the voxel's points is below this (rejects planes and blobs)."""
    min_round_ratio: float = Field(0.01, ge=0)
    """Line-like if lambda_min / lambda_mid is above this (a cross-section with some depth, also for a pole cut by a
    voxel boundary into a quarter arc; rejects noise-free plane strips).
    """
    max_thickness_m: float = Field(0.1, gt=0)
    """Line-like if sqrt((lambda_min + lambda_mid) / N), the RMS point-to-line distance, is below this (m): a pole seen
    from all round has its radius as RMS, so poles and posts up to 10 cm radius (street lights, sign posts); each scan
    sees a pole's near half, whose offset towards the sensor the association corrects.
    """
    max_direction_angle_deg: float = Field(10.0, gt=0, le=90)
    """Join touching line voxels whose directions differ at most this much (deg)."""
    max_line_distance_m: float = Field(0.1, gt=0)
    """Join touching line voxels whose centroids lie at most this far from each other's line (m)."""
    min_length_m: float = Field(1.5, gt=0)
    """Keep edge landmarks at least this long (m); short ones constrain the direction poorly."""
    max_point_distance_m: float = Field(0.15, gt=0)
    """Association: a point belongs to an edge when it lies at most this far from its line (m) and within its extent."""
    min_points_per_observation: int = Field(4, ge=2)
    """Points one scan needs on an edge to observe it."""
    min_elevation_spread_deg: float = Field(0.1, ge=0)
    """A scan observes an edge only when its points there span at least this elevation angle from the sensor (deg):
    points of one beam lie on one cone and trace a line across any surface (a ring on the ground); below the spacing of
    the beams of any multi-beam sensor, above one beam's jitter.
    """
    clearance_m: float = Field(0.5, gt=0)
    """Radius around a line that must be clear of other surfaces (m; at most voxel_size_m is used): a line is kept only
    when it stands free, so the centroid of its visible points does not move with the viewpoint (a wall corner, a kerb or
    the rim of a slab is seen from one side and belongs to its planes).
    """
    max_clearance_fraction: float = Field(0.25, ge=0)
    """Points between max_point_distance_m and clearance_m from a line may number at most this fraction of the points
    within max_point_distance_m (unitless; over the middle of its extent): room for stray returns at a pole's silhouette,
    far below the surfaces running away from a corner (several times the line's own points).
    """


class AssociationConfig(_Section):
    """When the rounds find and associate planes afresh and when they keep every point's plane."""

    rounds: int = Field(2, ge=1)
    """Rounds that find and associate planes afresh at the current poses, at least; later rounds keep every point's
    plane (a frozen association, so rounds cannot oscillate) and only re-deskew and re-adjust.
    """
    settle_m: float = Field(0.01, gt=0)
    """An association is frozen only when the round that used it moved no pose more than this (m); otherwise the
    next round associates afresh (up to max_rounds). It was made at poses that then moved by a sizeable part of the
    point gates (outlier_sigma times a landmark's thickness, a few cm), so points near a gate's edge may belong
    elsewhere at the new poses.
    """
    max_rounds: int = Field(8, ge=1)
    """Rounds that associate afresh at most, however far the poses still move: the association is frozen after this
    many rounds (or after `rounds`, when that is larger) whatever settle_m says, so rounds cannot oscillate. When its
    last fresh round still moved scans by more than settle_m, the rounds did not settle (the verdict cannot be
    `improved`); the report names those scans and sets their moves against the pose covariance's 3 sigma.
    """


class DeskewConfig(_Section):
    """The fixed point of the rounds with deskewing (sensor.deskew)."""

    max_contraction: float = Field(0.9, ge=0, lt=1)
    """Rounds with a frozen association and deskewing converge to the trajectory that reproduces itself when its own
    deskewed points are adjusted; from the third such round the next start is extrapolated (a secant step,
    `pa_cli.refine.deskew.DeskewFixedPoint`) when the measured contraction per round r is in (0, this], and not right
    after an extrapolation that left the change no smaller. The step is r / (1 - r) times the last change (9x at 0.9);
    0: no extrapolation.
    """


class RegistrationConfig(_Section):
    """The registrations of consecutive scans that measure the odometry factors' relative motions
    (`pa_cli.refine.pair_registration`)."""

    voxel_m: float = Field(0.5, gt=0)
    """Each pair is registered by GICP on the two scans' points downsampled to this voxel (m). About the spacing of a
    16-beam sensor's rings (2 deg) at a typical range (15 m outdoors: 0.5 m), so that a point's neighbours span rings
    rather than lie along one.
    """
    max_correspondence_m: float = Field(1.0, gt=0)
    """The registration pairs points at most this far apart (m): it starts from the initial trajectory's relative
    motion, within centimetres to decimetres of its result.
    """


class QualityConfig(_Section):
    """The quality verdict (`pa_cli.evaluation.quality`): cross-scored RMS, map entropy, odometry agreement."""

    start_check: bool = Field(True)
    """Solve the last round's problem again with the relative motions perturbed within the odometry's sigmas, from
    the refined poses (`pa_cli.refine.consistency`); scans that end beyond the pose covariance's 3 sigma make the
    verdict uncertain. Costs one more solve of a few iterations; off skips it.
    """

    outlier_sigma: float = Field(5.0, gt=0)
    """A consecutive pair whose relative motion the refinement changed by more than this many odometry sigmas is
    reported (the odometry or the refinement is wrong there; a doubt unless its shared planes carry more information
    than the odometry along the change); and a pair whose shared planes would not show a break of this many odometry
    sigmas (raise their cost by one point_sigma_m^2) is untied, a doubt.
    """
    rms_tolerance: float = Field(0.01, ge=0)
    """The refined map counts as worse when its RMS point-to-plane exceeds the initial poses' by more than this
    fraction on either plane set.
    """
    entropy_radius_m: float = Field(0.3, gt=0)
    """Mean map entropy: radius (m) of the neighbourhood around each query point. Several times the range noise and
    the pose errors to be seen (cm), below the size of the surfaces (a neighbourhood should hold one surface, not a
    corner); 0.3 m is the radius usual in the MME literature for LiDAR maps.
    """
    entropy_min_neighbours: int = Field(10, ge=4)
    """Mean map entropy: a query point counts when it has at least this many map points within the radius under both
    pose sets (fewer give an unreliable 3x3 covariance).
    """
    entropy_max_map_points: int = Field(1_000_000, ge=1000)
    """Mean map entropy: map points at most (a fixed pseudo-random subset of every scan, the same for both pose sets);
    bounds the neighbour searches. Short sequences keep every point: thinned to a tenth, the neighbourhoods of upright
    surfaces hold too few points to show a blur of a few centimetres.
    """
    entropy_query_points: int = Field(10_000, ge=100)
    """Mean map entropy: query points at most (drawn from the map points); both pose sets use the same queries, so
    their difference is steadier than either mean.
    """
    entropy_tolerance_nats: float = Field(0.03, ge=0)
    """The refined map counts as worse when its mean map entropy exceeds the initial poses' by more than this (nats);
    0.03 = 3 ln(1.01), every neighbourhood's standard deviations 1 % larger (as rms_tolerance).
    """
    entropy_standard_errors: float = Field(3.0, gt=0)
    """A class of surfaces (upright: walls, poles, trunks; level: ground, roofs) counts as blurrier (a doubt) when its
    mean map entropy rose from the initial to the refined poses by more than entropy_tolerance_nats and by more than
    this many standard errors of the mean per-point change; the standard error is the spread that the choice of query
    points gives, which exceeds 3 of them about once in 740 draws.
    """


class DegeneracyConfig(_Section):
    """Per-scan information: which directions the features hold and which they leave to the odometry."""

    lever_arm_m: float = Field(10.0, gt=0)
    """Lever arm (m) that turns rotations into metres in the per-scan information (a rotation of x rad moves a point
    this far away by x * this m): the typical distance of the points that constrain rotation.
    """


class SolverConfig(_Section):
    """Damped Newton (and the LM baseline): stopping rules and damping; the hierarchical backend's windows."""

    solver: Literal["newton", "lm", "hierarchical"] = Field("newton")
    """newton: planes eliminated; lm: PA_LM baseline; hierarchical: windows, keyframes and a global layer of newton
    (long sequences). `--solver` overrides it.
    """
    max_iterations: int = Field(100, ge=1)
    """Hessian solves (accepted or rejected) at most."""
    cost_tolerance: float = Field(1e-10, ge=0)
    """Stop when the relative cost decrease is below this."""
    gradient_tolerance: float = Field(1e-10, ge=0)
    """Stop when the max-norm of the gradient is below this (m^2/rad, m^2/m)."""
    step_tolerance: float = Field(1e-10, ge=0)
    """Stop when the 2-norm of the step (rad and m of all poses) is below this."""
    initial_damping: float = Field(1e-4, gt=0)
    """Initial mu, relative to the Hessian diagonal."""
    fixed_pose: int = Field(0, ge=0)
    """Index of the pose held fixed (gauge)."""
    eigen_gap_tolerance: float = Field(1e-6, ge=0)
    """Newton: clamp 1/(lambda_k - lambda_min) when the gap is below this times lambda_max (avoids blow-up for
    degenerate planes).
    """
    hierarchical_window_scans: int = Field(50, ge=2)
    """Hierarchical: consecutive scans per window (its core), refined together and collapsed into one keyframe; bounds
    the size of each window's system.
    """
    hierarchical_overlap_scans: int = Field(10, ge=0)
    """Hierarchical: scans on each side of a window's core refined with it (context; only the core's poses are kept),
    so the core's edge scans see planes on both sides.
    """
    hierarchical_cost_tolerance: float = Field(1e-8, ge=0)
    """Hierarchical: windows and the final flat pass stop when the relative cost decrease is below this (instead of
    cost_tolerance): every final iteration is a full flat one. Looser (1e-6) lets a heavily damped window stop far
    from its optimum.
    """
    hierarchical_cycles: int = Field(1, ge=1)
    """Hierarchical: window -> keyframe -> global cycles; every second cycle shifts the windows by half a core so the
    previous seams fall inside windows.
    """
    hierarchical_final_iterations: int = Field(10, ge=0)
    """Hierarchical: flat newton iterations over all scans (with the pose terms) from the hierarchical result, removing
    what the windows' rigid cores cannot; skipped with a warning when the estimated flat memory exceeds
    execution.memory_budget_gb.
    """
    hierarchical_min_scans: int = Field(3000, ge=2)
    """`pa refine` and `pa adjust` without --backend use the hierarchical backend from this many scans on (the flat
    system's time per iteration grows faster than the scans).
    """


class CovarianceConfig(_Section):
    """The pose covariance written next to the poses (MAP_covariance.npz)."""

    noise_model: Literal["auto", "range", "observation", "plane"] = Field("auto")
    """Point noise of the pose covariance, estimated from the residuals: range (each observation's variance spread
    over its points as noise along the beam, 1/|p|^2 with the sensor at the scan frame's origin, plus an isotropic
    part, their split measured from how the noise changes with the incidence), observation (one variance per scan
    and plane), plane (one per plane); auto: range when the association produced range clusters, else observation.
    Choose observation for scans whose frame origin is not the sensor.
    """
    max_block_products: float = Field(1e9, gt=0)
    """The most 6x6 block products its factorisation and selected inversion may take (each about 0.3 us of one core);
    above it, or when its block factor exceeds execution.memory_budget_gb, no covariance is computed (a warning). A
    sequential trajectory needs about 2,000 per scan; revisited places fill the factor towards dense (work cubic in
    the scans).
    """


class AdvancedExecutionConfig(_Section):
    """The point cache and the plane passes on dask workers."""

    cache_points: bool = Field(True)
    """Keep the scans' points in memory (float32, 12 bytes per point, up to execution.cache_budget_gb) after their
    first read, instead of re-reading the files two or three times per round.
    """
    window_scans: int = Field(100, ge=1)
    """Consecutive scans per task of plane association, and consecutive pairs per task of their registration, when
    tasks run on dask workers (each worker reads its window's scans from the source): a few seconds of work per task,
    small enough that a window's points are a small part of a worker's memory.
    """
    worker_cache_gb: float = Field(1.0, ge=0)
    """Points (float32) a worker keeps of the windows it read, so the association pass does not read them again after
    the detection pass (GB per worker; 0 or cache_points false: none).
    """


class LoopClosureConfig(_Section):
    """Loop closure (when loops.enabled): local maps, place descriptors, verification, pose graph."""

    local_map_length_m: float = Field(10.0, gt=0)
    """Odometry path length merged into one local map (m); long enough for a dense descriptor from a sparse sensor,
    short enough for odometry to be locally exact.
    """
    local_map_voxel_m: float = Field(0.5, gt=0)
    """Voxel size the local maps are thinned to (m), for the descriptors and the registrations' agreement;
    registration runs on the maps thinned to twice this. They need shapes, not points.
    """
    descriptor_range_m: float = Field(50.0, gt=0)
    """Radius of the polar height descriptor around a local map's anchor scan (m)."""
    descriptor_rings: int = Field(20, ge=2)
    """Radial bins of the polar descriptor (Scan Context rings)."""
    descriptor_sectors: int = Field(60, ge=8)
    """Angular bins of the polar descriptor (sectors); its yaw resolution is 360 deg / sectors."""
    descriptor_spacing_m: float = Field(2.0, gt=0)
    """Earlier local maps get a descriptor at viewpoints this far apart along their path (m), so a revisit passing off
    the anchor still finds one within half this; a polar descriptor tolerates about a metre of offset.
    """
    candidates_per_query: int = Field(3, ge=1)
    """Earlier local maps proposed per local map (nearest descriptors); more than one lets the ambiguity test see
    look-alike places. The two nearest are registered; the others only when those two do not both pass (a place
    driven for the tenth time has more earlier visits than it needs closures).
    """
    max_descriptor_distance: float = Field(0.35, gt=0, le=1)
    """Propose a pair only when the column-shifted cosine distance of their descriptors is below this (0 identical, 1
    unrelated).
    """
    bev_cell_m: float = Field(1.0, gt=0)
    """Cell of the bird's-eye occupancy images correlated for the initial translation of a candidate (m)."""
    max_correspondence_m: float = Field(1.0, gt=0)
    """Registration: largest point-to-point distance used as a correspondence (m), after the coarse pass at four times
    this.
    """
    inlier_distance_m: float = Field(0.2, gt=0)
    """A registered point is an inlier when it lies this close to the other local map's surface (m, point to plane): a
    few times the sensor noise plus the odometry's error within a local map.
    """
    overlap_distance_m: float = Field(2.0, gt=0)
    """A registered point is in the overlap when its nearest neighbour is this close (m); fitness is inliers /
    overlapping points.
    """
    min_fitness: float = Field(0.8, gt=0, le=1)
    """Accept a registration only when this fraction of the overlapping points are inliers."""
    min_overlap: float = Field(0.3, gt=0, le=1)
    """Accept a registration only when this fraction of the query local map overlaps the reference."""
    max_drift_fraction: float = Field(0.1, gt=0)
    """Odometry drift bound: a closure may move one local map relative to the other by at most this fraction of the path
    between them (along the odometry and the closures accepted so far), plus drift_floor_m (m/m).
    """
    drift_floor_m: float = Field(2.0, ge=0)
    """Odometry drift bound: the allowance at zero path length (m), the registration's pull-in range."""
    max_drift_deg_per_m: float = Field(0.1, gt=0)
    """Odometry drift bound on the rotation correction (deg per m of path between the local maps), plus drift_floor_deg.
    """
    drift_floor_deg: float = Field(2.0, ge=0)
    """Odometry drift bound: the rotation allowance at zero path length (deg)."""
    odometry_min_step_m: float = Field(0.1, gt=0)
    """Pose graph: an odometry step counts as at least this long for its sigmas (m); a standing sensor's scan matching
    still has noise.
    """
    odometry_translation_sigma_m: float = Field(0.1, gt=0)
    """Pose graph: 1-sigma of one odometry step's translation per sqrt(m) travelled (m); loose against the loop sigmas,
    so a verified closure takes the drift it ends instead of sharing it (odometry drift is systematic, and a closure
    left metres off would fall into the kernel's tail).
    """
    odometry_rotation_sigma_deg: float = Field(0.5, gt=0)
    """Pose graph: 1-sigma of one odometry step's rotation per sqrt(m) travelled (deg); loose for the same reason."""
    loop_translation_sigma_m: float = Field(0.1, gt=0)
    """Pose graph: 1-sigma of a verified closure's translation (m)."""
    loop_rotation_sigma_deg: float = Field(0.5, gt=0)
    """Pose graph: 1-sigma of a verified closure's rotation (deg)."""
    robust_kernel_sigmas: float = Field(3.0, gt=0)
    """Pose graph: Cauchy kernel width on loop edges, in loop sigmas; a closure that disagrees by more is down-weighted.
    """


class CalibrateConfig(_Section):
    """Multi-LiDAR extrinsic calibration (`pa calibrate`): scan matching, coarse ICP, rounds, observability."""

    time_match_tolerance_s: float = Field(0.02, gt=0)
    """Scans of two LiDARs are matched by `times.txt` when both have one: a scan pairs with the base scan nearest in
    time if they are at most this far apart (s); about a fifth of a 10 Hz sweep, so a pair sees nearly the same pose.
    """
    max_rounds: int = Field(5, ge=1)
    """Rounds of (plane association at the composite poses, joint adjustment) at most."""
    settle_translation_m: float = Field(1e-4, gt=0)
    """The rounds stop when no base pose and no extrinsic moved more than this in a round (m); a tenth of a millimetre,
    below the accuracy the extrinsics are wanted to.
    """
    settle_rotation_deg: float = Field(1e-3, gt=0)
    """The rounds stop when no base pose and no extrinsic turned more than this in a round (deg)."""
    lever_arm_m: float = Field(10.0, gt=0)
    """Lever arm (m) that turns extrinsic rotations into metres (x rad moves a point this far away by x * this m) in the
    observability analysis and the coarse stage's convergence test: the typical range of the points that constrain it.
    """
    unobservable_sigma_m: float = Field(0.05, gt=0)
    """A direction of an extrinsic whose predicted 1-sigma (point noise advanced.odometry.point_sigma_m; rotations at
    lever_arm_m) exceeds this (m) is unobservable: reported in words and held at its initial value instead of
    estimated.
    """
    coarse_voxel_m: float = Field(0.2, gt=0)
    """Coarse ICP: voxel of the downsampled lidar0 map and of the other LiDARs' scans (m)."""
    coarse_neighbours: int = Field(10, ge=4)
    """Coarse ICP: neighbours of a map point whose spread gives its normal and planarity
    (advanced.planes.max_eigen_ratio)."""
    coarse_max_distance_m: float = Field(2.0, gt=0)
    """Coarse ICP: first correspondence distance (m); a 5 deg error moves a point 20 m away by 1.7 m."""
    coarse_min_distance_m: float = Field(0.2, gt=0)
    """Coarse ICP: last correspondence distance (m), about the coarse voxel; the joint adjustment takes it from there."""
    coarse_max_iterations: int = Field(60, ge=1)
    """Coarse ICP: Gauss-Newton iterations at most, over all correspondence distances."""


class AdvancedConfig(_Section):
    """Every other tunable, by the part of the program that uses it (docs/config.md)."""

    kiss_icp: KissIcpConfig = KissIcpConfig()
    odometry: OdometryConfig = OdometryConfig()
    planes: AdvancedPlanesConfig = AdvancedPlanesConfig()
    edges: EdgesConfig = EdgesConfig()
    association: AssociationConfig = AssociationConfig()
    deskew: DeskewConfig = DeskewConfig()
    registration: RegistrationConfig = RegistrationConfig()
    quality: QualityConfig = QualityConfig()
    degeneracy: DegeneracyConfig = DegeneracyConfig()
    solver: SolverConfig = SolverConfig()
    covariance: CovarianceConfig = CovarianceConfig()
    execution: AdvancedExecutionConfig = AdvancedExecutionConfig()
    loops: LoopClosureConfig = LoopClosureConfig()
    calibrate: CalibrateConfig = CalibrateConfig()


class PaConfig(_Section):
    """The configuration of `pa`: the user-facing sections, then `advanced`."""

    sensor: SensorConfig = SensorConfig()
    scene: SceneConfig = SceneConfig()
    refine: RefineConfig = RefineConfig()
    loops: LoopsConfig = LoopsConfig()
    map: MapConfig = MapConfig()
    execution: ExecutionConfig = ExecutionConfig()
    advanced: AdvancedConfig = AdvancedConfig()

    def planes_config(self) -> PlanesConfig:
        """What the plane code takes: `advanced.planes` with the scene's plane voxel and thickness and
        `execution.threads`."""
        return PlanesConfig(**dict(self.advanced.planes), voxel_size_m=self.scene.plane_voxel_m,
                            max_thickness_m=self.scene.max_plane_thickness_m,
                            association_threads=self.execution.threads)

    def edges_config(self) -> EdgesConfig | None:
        """`advanced.edges` when scene.edges is true or auto, else None (no edges)."""
        return None if self.scene.edges is False else self.advanced.edges


USER_SECTIONS = tuple(name for name in PaConfig.model_fields if name != "advanced")
"""The sections a user is expected to set, in the order `pa config show` prints them."""
