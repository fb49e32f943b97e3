"""Where every key of pa 0.1 went in pa 0.2: the one place a config file's old keys are looked up.

`RENAMED` maps an old dotted key to its new dotted key; `CONSTANTS` maps an old key that is no
longer a setting to the module constant that replaced it (module path, name); `REMOVED` maps a key
whose mechanism was removed (under its pa 0.1 name and its later one) to why. Old keys in none of
them kept their place (`refine.max_rounds`, `loops.enabled`, `execution.workers`, ...). Loading a
file that uses an old key is an error that names the new key, the constant or why it went
(`pa_cli.config.load`).
"""

from __future__ import annotations

RENAMED_IN = "pa 0.2"

RENAMED: dict[str, str] = {
    # odometry: the sensor's ranges are user-facing, KISS-ICP's own settings advanced
    "odometry.max_range_m": "sensor.max_range_m",
    "odometry.min_range_m": "sensor.min_range_m",
    "odometry.voxel_size_m": "advanced.kiss_icp.voxel_size_m",
    "odometry.deskew": "advanced.kiss_icp.deskew",
    # planes: the voxel and thickness are the scene's, the threads execution's
    "planes.voxel_size_m": "scene.plane_voxel_m",
    "planes.max_thickness_m": "scene.max_plane_thickness_m",
    "planes.association_threads": "execution.threads",
    "planes.max_subdivision_levels": "advanced.planes.max_subdivision_levels",
    "planes.min_points": "advanced.planes.min_points",
    "planes.max_eigen_ratio": "advanced.planes.max_eigen_ratio",
    "planes.max_normal_angle_deg": "advanced.planes.max_normal_angle_deg",
    "planes.max_plane_distance_m": "advanced.planes.max_plane_distance_m",
    "planes.neighbourhood": "advanced.planes.neighbourhood",
    "planes.max_split_rounds": "advanced.planes.max_split_rounds",
    "planes.leaf_outlier_sigma": "advanced.planes.leaf_outlier_sigma",
    "planes.leaf_refit_rounds": "advanced.planes.leaf_refit_rounds",
    "planes.grow_into_sparse": "advanced.planes.grow_into_sparse",
    "planes.min_points_per_observation": "advanced.planes.min_points_per_observation",
    "planes.outlier_sigma": "advanced.planes.outlier_sigma",
    "planes.outlier_sigma_floor_m": "advanced.planes.outlier_sigma_floor_m",
    "planes.max_normal_uncertainty_deg": "advanced.planes.max_normal_uncertainty_deg",
    "planes.refit_min_kept_fraction": "advanced.planes.refit_min_kept_fraction",
    "planes.tilted_thickness_fraction": "advanced.planes.tilted_thickness_fraction",
    "planes.side_grazing_angle_deg": "advanced.planes.side_grazing_angle_deg",
    "planes.min_constraint_eigenvalue": "advanced.planes.min_constraint_eigenvalue",
    # edges: on/off is the scene's
    "edges.enabled": "scene.edges",
    "edges.voxel_size_m": "advanced.edges.voxel_size_m",
    "edges.min_points": "advanced.edges.min_points",
    "edges.max_mid_ratio": "advanced.edges.max_mid_ratio",
    "edges.min_round_ratio": "advanced.edges.min_round_ratio",
    "edges.max_thickness_m": "advanced.edges.max_thickness_m",
    "edges.max_direction_angle_deg": "advanced.edges.max_direction_angle_deg",
    "edges.max_line_distance_m": "advanced.edges.max_line_distance_m",
    "edges.min_length_m": "advanced.edges.min_length_m",
    "edges.max_point_distance_m": "advanced.edges.max_point_distance_m",
    "edges.min_points_per_observation": "advanced.edges.min_points_per_observation",
    "edges.min_elevation_spread_deg": "advanced.edges.min_elevation_spread_deg",
    "edges.clearance_m": "advanced.edges.clearance_m",
    "edges.max_clearance_fraction": "advanced.edges.max_clearance_fraction",
    # solver: the memory budget is execution's, the covariance its own subsection
    "solver.solver": "advanced.solver.solver",
    "solver.max_iterations": "advanced.solver.max_iterations",
    "solver.cost_tolerance": "advanced.solver.cost_tolerance",
    "solver.gradient_tolerance": "advanced.solver.gradient_tolerance",
    "solver.step_tolerance": "advanced.solver.step_tolerance",
    "solver.initial_damping": "advanced.solver.initial_damping",
    "solver.fixed_pose": "advanced.solver.fixed_pose",
    "solver.eigen_gap_tolerance": "advanced.solver.eigen_gap_tolerance",
    "solver.hierarchical_window_scans": "advanced.solver.hierarchical_window_scans",
    "solver.hierarchical_overlap_scans": "advanced.solver.hierarchical_overlap_scans",
    "solver.hierarchical_cost_tolerance": "advanced.solver.hierarchical_cost_tolerance",
    "solver.hierarchical_cycles": "advanced.solver.hierarchical_cycles",
    "solver.hierarchical_final_iterations": "advanced.solver.hierarchical_final_iterations",
    "solver.hierarchical_min_scans": "advanced.solver.hierarchical_min_scans",
    "solver.memory_budget_gb": "execution.memory_budget_gb",
    "solver.covariance_max_block_products": "advanced.covariance.max_block_products",
    # refine: the prefixes that were sections in disguise are subsections of advanced
    "refine.association_rounds": "advanced.association.rounds",
    "refine.association_settle_m": "advanced.association.settle_m",
    "refine.max_association_rounds": "advanced.association.max_rounds",
    "refine.map_voxel_m": "map.voxel_m",
    "refine.cache_points": "advanced.execution.cache_points",
    "refine.cache_budget_gb": "execution.cache_budget_gb",
    "refine.deskew": "sensor.deskew",
    "refine.deskew_max_contraction": "advanced.deskew.max_contraction",
    "refine.point_sigma_m": "advanced.odometry.point_sigma_m",
    "refine.odometry_translation_sigma_per_m": "advanced.odometry.translation_sigma_per_m",
    "refine.odometry_rotation_sigma_per_deg": "advanced.odometry.rotation_sigma_per_deg",
    "refine.odometry_rotation_sigma_deg_per_m": "advanced.odometry.rotation_sigma_deg_per_m",
    "refine.covariance_noise_model": "advanced.covariance.noise_model",
    "refine.degeneracy_lever_arm_m": "advanced.degeneracy.lever_arm_m",
    "refine.quality_outlier_sigma": "advanced.quality.outlier_sigma",
    "refine.quality_rms_tolerance": "advanced.quality.rms_tolerance",
    "refine.quality_entropy_radius_m": "advanced.quality.entropy_radius_m",
    "refine.quality_entropy_min_neighbours": "advanced.quality.entropy_min_neighbours",
    "refine.quality_entropy_max_map_points": "advanced.quality.entropy_max_map_points",
    "refine.quality_entropy_query_points": "advanced.quality.entropy_query_points",
    "refine.quality_entropy_tolerance_nats": "advanced.quality.entropy_tolerance_nats",
    "refine.quality_entropy_standard_errors": "advanced.quality.entropy_standard_errors",
    "refine.hold_registration_voxel_m": "advanced.registration.voxel_m",
    "refine.hold_registration_max_correspondence_m": "advanced.registration.max_correspondence_m",
    # loops: on/off and the separation are user-facing, the rest advanced
    "loops.min_loop_separation_m": "loops.min_separation_m",
    "loops.local_map_length_m": "advanced.loops.local_map_length_m",
    "loops.local_map_voxel_m": "advanced.loops.local_map_voxel_m",
    "loops.descriptor_range_m": "advanced.loops.descriptor_range_m",
    "loops.descriptor_rings": "advanced.loops.descriptor_rings",
    "loops.descriptor_sectors": "advanced.loops.descriptor_sectors",
    "loops.descriptor_spacing_m": "advanced.loops.descriptor_spacing_m",
    "loops.candidates_per_query": "advanced.loops.candidates_per_query",
    "loops.max_descriptor_distance": "advanced.loops.max_descriptor_distance",
    "loops.bev_cell_m": "advanced.loops.bev_cell_m",
    "loops.max_correspondence_m": "advanced.loops.max_correspondence_m",
    "loops.inlier_distance_m": "advanced.loops.inlier_distance_m",
    "loops.overlap_distance_m": "advanced.loops.overlap_distance_m",
    "loops.min_fitness": "advanced.loops.min_fitness",
    "loops.min_overlap": "advanced.loops.min_overlap",
    "loops.max_drift_fraction": "advanced.loops.max_drift_fraction",
    "loops.drift_floor_m": "advanced.loops.drift_floor_m",
    "loops.max_drift_deg_per_m": "advanced.loops.max_drift_deg_per_m",
    "loops.drift_floor_deg": "advanced.loops.drift_floor_deg",
    "loops.odometry_min_step_m": "advanced.loops.odometry_min_step_m",
    "loops.odometry_translation_sigma_m": "advanced.loops.odometry_translation_sigma_m",
    "loops.odometry_rotation_sigma_deg": "advanced.loops.odometry_rotation_sigma_deg",
    "loops.loop_translation_sigma_m": "advanced.loops.loop_translation_sigma_m",
    "loops.loop_rotation_sigma_deg": "advanced.loops.loop_rotation_sigma_deg",
    "loops.robust_kernel_sigmas": "advanced.loops.robust_kernel_sigmas",
    # execution: the dask plane passes are advanced
    "execution.association_window_scans": "advanced.execution.window_scans",
    "execution.worker_cache_gb": "advanced.execution.worker_cache_gb",
    # calibrate: all advanced
    "calibrate.time_match_tolerance_s": "advanced.calibrate.time_match_tolerance_s",
    "calibrate.max_rounds": "advanced.calibrate.max_rounds",
    "calibrate.settle_translation_m": "advanced.calibrate.settle_translation_m",
    "calibrate.settle_rotation_deg": "advanced.calibrate.settle_rotation_deg",
    "calibrate.lever_arm_m": "advanced.calibrate.lever_arm_m",
    "calibrate.unobservable_sigma_m": "advanced.calibrate.unobservable_sigma_m",
    "calibrate.coarse_voxel_m": "advanced.calibrate.coarse_voxel_m",
    "calibrate.coarse_neighbours": "advanced.calibrate.coarse_neighbours",
    "calibrate.coarse_max_distance_m": "advanced.calibrate.coarse_max_distance_m",
    "calibrate.coarse_min_distance_m": "advanced.calibrate.coarse_min_distance_m",
    "calibrate.coarse_max_iterations": "advanced.calibrate.coarse_max_iterations",
}

CONSTANTS: dict[str, tuple[str, str]] = {
    "refine.map_chunk_points": ("pa_cli/io/maps.py", "MAP_CHUNK_POINTS"),
    "refine.deskew_max_sweep_s": ("pa_cli/refine/deskew.py", "MAX_SWEEP_S"),
    "refine.quality_entropy_min_sigma_m": ("pa_cli/evaluation/quality.py", "ENTROPY_MIN_SIGMA_M"),
    "calibrate.coarse_damping": ("pa_cli/calibration/coarse.py", "COARSE_DAMPING"),
}

_RELOCALISATION_REMOVED = ("the search for scans the planes lost was removed: the rounds start from the chain of the "
                           "motions registered per pair, which holds such scans (docs/trust.md#scans-the-planes-lost)")

REMOVED: dict[str, str] = {
    "refine.relocalise_search_m": _RELOCALISATION_REMOVED,
    "refine.relocalise_step_m": _RELOCALISATION_REMOVED,
    "refine.relocalise_max_group_scans": _RELOCALISATION_REMOVED,
    "advanced.relocalise.search_m": _RELOCALISATION_REMOVED,
    "advanced.relocalise.step_m": _RELOCALISATION_REMOVED,
    "advanced.relocalise.max_group_scans": _RELOCALISATION_REMOVED,
}
