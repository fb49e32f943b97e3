"""The config: presets shipped in the package, keys of pa 0.1 refused with their new place, unknown
keys with the closest valid one, `pa config show` and MAP_config.yaml loading back, units and
descriptions of every key, docs/config.md current."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import pytest
import yaml

from docs.make_config_reference import PAGE, render, unit_of
from pa_cli.config import (
    CONSTANTS,
    REMOVED,
    RENAMED,
    USER_SECTIONS,
    PaConfig,
    dotted_keys,
    dump_config,
    load_config,
    preset_names,
)
from pa_cli.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]

# every key of pa 0.1 with its default there: each must keep its default at its new place
OLD_DEFAULTS = {
    "odometry.max_range_m": 100.0,
    "odometry.min_range_m": 0.5,
    "odometry.voxel_size_m": None,
    "odometry.deskew": False,
    "planes.voxel_size_m": 1.0,
    "planes.max_subdivision_levels": 2,
    "planes.min_points": 10,
    "planes.max_eigen_ratio": 0.05,
    "planes.max_thickness_m": 0.05,
    "planes.max_normal_angle_deg": 10.0,
    "planes.max_plane_distance_m": 0.05,
    "planes.neighbourhood": 26,
    "planes.max_split_rounds": 20,
    "planes.leaf_outlier_sigma": 2.0,
    "planes.leaf_refit_rounds": 3,
    "planes.grow_into_sparse": True,
    "planes.min_points_per_observation": 10,
    "planes.outlier_sigma": 3.0,
    "planes.outlier_sigma_floor_m": 0.002,
    "planes.max_normal_uncertainty_deg": 1.0,
    "planes.refit_min_kept_fraction": 0.75,
    "planes.tilted_thickness_fraction": 0.5,
    "planes.side_grazing_angle_deg": 10.0,
    "planes.association_threads": 2,
    "planes.min_constraint_eigenvalue": 0.1,
    "edges.enabled": False,
    "edges.voxel_size_m": 1.0,
    "edges.min_points": 8,
    "edges.max_mid_ratio": 0.05,
    "edges.min_round_ratio": 0.01,
    "edges.max_thickness_m": 0.1,
    "edges.max_direction_angle_deg": 10.0,
    "edges.max_line_distance_m": 0.1,
    "edges.min_length_m": 1.5,
    "edges.max_point_distance_m": 0.15,
    "edges.min_points_per_observation": 4,
    "edges.min_elevation_spread_deg": 0.1,
    "edges.clearance_m": 0.5,
    "edges.max_clearance_fraction": 0.25,
    "solver.solver": 'newton',
    "solver.max_iterations": 100,
    "solver.cost_tolerance": 1e-10,
    "solver.gradient_tolerance": 1e-10,
    "solver.step_tolerance": 1e-10,
    "solver.initial_damping": 0.0001,
    "solver.fixed_pose": 0,
    "solver.eigen_gap_tolerance": 1e-06,
    "solver.hierarchical_window_scans": 50,
    "solver.hierarchical_overlap_scans": 10,
    "solver.hierarchical_cost_tolerance": 1e-08,
    "solver.hierarchical_cycles": 1,
    "solver.hierarchical_final_iterations": 10,
    "solver.hierarchical_min_scans": 3000,
    "solver.memory_budget_gb": 8.0,
    "solver.covariance_max_block_products": 1000000000.0,
    "refine.max_rounds": 10,
    "refine.association_rounds": 2,
    "refine.association_settle_m": 0.01,
    "refine.max_association_rounds": 4,
    "refine.pose_change_tolerance_m": 0.001,
    "refine.pose_change_tolerance_deg": 0.01,
    "refine.map_voxel_m": 0.1,
    "refine.map_chunk_points": 1000000,
    "refine.cache_points": True,
    "refine.deskew": 'auto',
    "refine.deskew_max_sweep_s": 2.0,
    "refine.deskew_max_contraction": 0.9,
    "refine.point_sigma_m": 0.1,
    "refine.odometry_translation_sigma_m": 0.05,
    "refine.odometry_translation_sigma_per_m": 0.02,
    "refine.odometry_rotation_sigma_deg": 0.5,
    "refine.odometry_rotation_sigma_per_deg": 0.05,
    "refine.odometry_rotation_sigma_deg_per_m": 0.02,
    "refine.covariance_noise_model": 'auto',
    "refine.degeneracy_lever_arm_m": 10.0,
    "refine.relocalise_search_m": 3.0,
    "refine.relocalise_step_m": 0.02,
    "refine.relocalise_max_group_scans": 4,
    "refine.quality_outlier_sigma": 5.0,
    "refine.quality_rms_tolerance": 0.01,
    "refine.quality_entropy_radius_m": 0.3,
    "refine.quality_entropy_min_neighbours": 10,
    "refine.quality_entropy_max_map_points": 1000000,
    "refine.quality_entropy_query_points": 10000,
    "refine.quality_entropy_min_sigma_m": 0.001,
    "refine.quality_entropy_tolerance_nats": 0.03,
    "refine.quality_entropy_standard_errors": 3.0,
    "refine.hold_registration_voxel_m": 0.5,
    "refine.hold_registration_max_correspondence_m": 1.0,
    "refine.cache_budget_gb": 4.0,
    "loops.enabled": False,
    "loops.local_map_length_m": 10.0,
    "loops.local_map_voxel_m": 0.5,
    "loops.descriptor_range_m": 50.0,
    "loops.descriptor_rings": 20,
    "loops.descriptor_sectors": 60,
    "loops.descriptor_spacing_m": 2.0,
    "loops.candidates_per_query": 5,
    "loops.max_descriptor_distance": 0.35,
    "loops.min_loop_separation_m": 50.0,
    "loops.bev_cell_m": 1.0,
    "loops.max_correspondence_m": 1.0,
    "loops.inlier_distance_m": 0.2,
    "loops.overlap_distance_m": 2.0,
    "loops.min_fitness": 0.8,
    "loops.min_overlap": 0.3,
    "loops.max_drift_fraction": 0.1,
    "loops.drift_floor_m": 2.0,
    "loops.max_drift_deg_per_m": 0.1,
    "loops.drift_floor_deg": 2.0,
    "loops.odometry_min_step_m": 0.1,
    "loops.odometry_translation_sigma_m": 0.1,
    "loops.odometry_rotation_sigma_deg": 0.5,
    "loops.loop_translation_sigma_m": 0.1,
    "loops.loop_rotation_sigma_deg": 0.5,
    "loops.robust_kernel_sigmas": 3.0,
    "execution.workers": 0,
    "execution.scheduler_address": None,
    "execution.threads_per_worker": 1,
    "execution.association_window_scans": 100,
    "execution.worker_cache_gb": 1.0,
    "calibrate.time_match_tolerance_s": 0.02,
    "calibrate.max_rounds": 5,
    "calibrate.settle_translation_m": 0.0001,
    "calibrate.settle_rotation_deg": 0.001,
    "calibrate.lever_arm_m": 10.0,
    "calibrate.unobservable_sigma_m": 0.05,
    "calibrate.coarse_voxel_m": 0.2,
    "calibrate.coarse_neighbours": 10,
    "calibrate.coarse_max_distance_m": 2.0,
    "calibrate.coarse_min_distance_m": 0.2,
    "calibrate.coarse_max_iterations": 60,
    "calibrate.coarse_damping": 1e-06,
}

# keys that pa 0.1 did not have
ADDED_SINCE_0_1 = {"advanced.quality.start_check", "advanced.odometry.measurements"}

# keys of pa 0.1 whose default changed since (at the old key), with the new default
CHANGED_SINCE_0_1 = {"loops.candidates_per_query": 3, "refine.max_rounds": 15, "refine.max_association_rounds": 8,
                     "loops.enabled": True, "edges.enabled": "auto", "planes.max_split_rounds": 100}

# what configs/indoor.yaml and configs/outdoor.yaml of pa 0.1 set, at the new keys
PRESET_VALUES = {
    "indoor": {"sensor.max_range_m": 30.0, "sensor.min_range_m": 0.3, "advanced.kiss_icp.voxel_size_m": 0.1,
               "scene.plane_voxel_m": 0.5, "advanced.planes.max_normal_uncertainty_deg": 0.25, "map.voxel_m": 0.05,
               "advanced.registration.voxel_m": 0.25},
    "outdoor": {"sensor.max_range_m": 100.0, "sensor.min_range_m": 2.0, "scene.plane_voxel_m": 1.0,
                "map.voxel_m": 0.2},
}


def _value(config: PaConfig, dotted: str):
    value = config
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "my.yaml"
    path.write_text(text)
    return path


def _refused(path: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert "Extra inputs" not in message and "extra_forbidden" not in message
    return message


# ------------------------------------------------------------------------------------------------ presets


@pytest.mark.parametrize("name", ["indoor", "outdoor"])
def test_each_preset_loads_and_sets_what_pa_0_1_set(name):
    assert name in preset_names()
    config = load_config(name)
    changed = {key for key in dotted_keys() if _value(config, key) != _value(PaConfig(), key)}
    expected = PRESET_VALUES[name]
    assert {key: _value(config, key) for key in expected} == expected
    assert changed <= set(expected)  # nothing else differs from the defaults


def _flat(mapping: dict, prefix: str = "") -> dict:
    """A nested mapping as {dotted key: value}."""
    flat = {}
    for key, value in mapping.items():
        flat.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return flat


def test_presets_hold_only_what_differs_from_the_defaults():
    for name in preset_names():
        data = yaml.safe_load((REPO / "pa_cli" / "presets" / f"{name}.yaml").read_text())
        assert all(_value(PaConfig(), key) != value for key, value in _flat(data).items()), name


def test_a_missing_path_that_is_no_preset_lists_the_presets(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.yaml: no such config file, and not a preset \(presets: indoor, "
                                          r"outdoor\).*--config indoor\|outdoor\|PATH"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="presets: indoor, outdoor"):
        load_config("indor")


@pytest.mark.slow
def test_refine_with_a_preset_from_a_folder_outside_the_checkout(run_pa, tmp_path, monkeypatch):
    from pa_testing.room_scene import write_room_folder

    room = write_room_folder(tmp_path)
    work = tmp_path / "elsewhere"  # not the checkout: the preset comes from the package
    work.mkdir()
    monkeypatch.chdir(work)
    code, _, err = run_pa("refine", room / "scans", "--out", "map.ply", "--config", "outdoor", "--poses",
                          room / "gt_kitti.txt", "--rounds", "2", "-q")
    assert code == 0, err
    report = json.loads((work / "map_report.json").read_text())
    assert report["input"]["config"] == "outdoor" and report["map"]["voxel_m"] == 0.2
    written = load_config(work / "map_config.yaml")  # the effective config loads back, every key equal
    expected = load_config("outdoor")
    expected.refine.max_rounds = 2
    assert written == expected


# ------------------------------------------------------------------------------------------------ old keys


def test_every_old_key_moved_became_a_constant_or_kept_its_place():
    valid = set(dotted_keys())
    assert set(RENAMED) | set(CONSTANTS) <= set(OLD_DEFAULTS)
    assert not set(REMOVED) & valid  # a removed key is no setting
    kept = set(OLD_DEFAULTS) - set(RENAMED) - set(CONSTANTS) - set(REMOVED)
    assert kept <= valid, kept - valid
    assert set(RENAMED.values()) <= valid, set(RENAMED.values()) - valid
    assert len(set(RENAMED.values())) == len(RENAMED)  # no two old keys merged into one
    assert valid - set(RENAMED.values()) - kept == ADDED_SINCE_0_1  # no other key added


def test_every_default_is_the_one_of_pa_0_1_unless_changed_since():
    config = PaConfig()
    assert set(CHANGED_SINCE_0_1) <= set(OLD_DEFAULTS)
    for old, default in {**OLD_DEFAULTS, **CHANGED_SINCE_0_1}.items():
        if old in REMOVED:
            continue
        if old in CONSTANTS:
            module, name = CONSTANTS[old]
            value = getattr(importlib.import_module(module.removesuffix(".py").replace("/", ".")), name)
        else:
            value = _value(config, RENAMED.get(old, old))
        assert value == default and type(value) is type(default), old


@pytest.mark.parametrize("old", sorted(RENAMED))
def test_a_renamed_key_names_its_new_place(tmp_path, old):
    section, key = old.split(".")
    path = _write(tmp_path, yaml.safe_dump({section: {key: OLD_DEFAULTS[old]}}))
    assert f"{path}: `{old}` was renamed to `{RENAMED[old]}` (pa 0.2)." in _refused(path)


@pytest.mark.parametrize("old", sorted(CONSTANTS))
def test_a_key_turned_constant_names_the_constant(tmp_path, old):
    section, key = old.split(".")
    path = _write(tmp_path, yaml.safe_dump({section: {key: OLD_DEFAULTS[old]}}))
    module, name = CONSTANTS[old]
    assert f"{path}: `{old}` is no longer a setting (pa 0.2): it is the constant {name} in {module}." \
        in _refused(path)


@pytest.mark.parametrize("old", sorted(REMOVED))
def test_a_removed_key_says_why(tmp_path, old):
    *sections, key = old.split(".")
    data = {key: 1.0}
    for section in reversed(sections):
        data = {section: data}
    path = _write(tmp_path, yaml.safe_dump(data))
    assert f"{path}: `{old}` is no longer a setting (pa 0.2): {REMOVED[old]}" in _refused(path)


def test_a_file_of_pa_0_1_gets_one_line_per_old_key(tmp_path):
    path = _write(tmp_path, "odometry: {max_range_m: 30.0}\nplanes: {voxel_size_m: 0.5}\n"
                            "refine: {max_rounds: 3, map_voxel_m: 0.05}\n")
    message = _refused(path)
    assert [line.split(": ", 1)[1] for line in message.splitlines()[:3]] == [
        "`odometry.max_range_m` was renamed to `sensor.max_range_m` (pa 0.2).",
        "`planes.voxel_size_m` was renamed to `scene.plane_voxel_m` (pa 0.2).",
        "`refine.map_voxel_m` was renamed to `map.voxel_m` (pa 0.2)."]
    assert "pa config show --advanced" in message.splitlines()[-1]


# ------------------------------------------------------------------------------------------------ unknown keys


@pytest.mark.parametrize("text, unknown, suggested", [
    ("sensor: {max_range: 30}\n", "sensor.max_range", "sensor.max_range_m"),
    ("advanced: {planes: {min_point: 5}}\n", "advanced.planes.min_point", "advanced.planes.min_points"),
    ("sensr: {max_range_m: 30}\n", "sensr", "sensor"),
    ("planes: {voxel_size: 1.0}\n", "planes.voxel_size", "scene.plane_voxel_m"),  # close to an old key
    ("refine: {entropy_radius_m: 0.5}\n", "refine.entropy_radius_m", "advanced.quality.entropy_radius_m"),
])
def test_an_unknown_key_gets_the_closest_valid_one(tmp_path, text, unknown, suggested):
    path = _write(tmp_path, text)
    message = _refused(path)
    assert message.startswith(f"{path}: unknown key `{unknown}`; did you mean `{suggested}`")


def test_a_bad_value_names_the_key_and_the_value(tmp_path):
    message = _refused(_write(tmp_path, "sensor: {max_range_m: -1}\nscene: {edges: maybe}\n"))
    assert "`sensor.max_range_m`: Input should be greater than 0 (got -1)" in message
    assert "`scene.edges`" in message


def test_a_section_with_every_key_commented_out_is_empty(tmp_path):
    config = load_config(_write(tmp_path, "sensor:\n#  max_range_m: 30\nadvanced:\n  planes:\n"))
    assert config == PaConfig()


# ------------------------------------------------------------------------------------------------ dump, show


@pytest.mark.parametrize("source", [None, "indoor", "outdoor"])
@pytest.mark.parametrize("advanced", [False, True])
def test_config_show_loads_back_to_the_same_config(run_pa, tmp_path, source, advanced):
    code, out, err = run_pa("config", "show", *([source] if source else []), *(["--advanced"] if advanced else []))
    assert code == 0, err
    assert list(yaml.safe_load(out))[:len(USER_SECTIONS)] == list(USER_SECTIONS)  # user-facing sections first
    assert load_config(_write(tmp_path, out)) == load_config(source)
    assert ("planes:" in out) == (advanced or source == "indoor")  # advanced keys: all, or those changed


def test_config_show_of_a_file(run_pa, tmp_path):
    path = _write(tmp_path, "refine: {max_rounds: 3}\nadvanced: {solver: {max_iterations: 7}}\n")
    code, out, _ = run_pa("config", "show", path)
    assert code == 0 and f"# pa config: {path}." in out
    assert "  max_rounds: 3  # Rounds" in out and "    max_iterations: 7  # Hessian solves" in out
    code, _, err = run_pa("config", "show", tmp_path / "nope.yaml")
    assert code == 1 and "not a preset (presets: indoor, outdoor)" in err


def test_the_dump_of_every_key_changed_loads_back():
    config = load_config("indoor")
    config.sensor.deskew = "off"
    config.refine.odometry_translation_sigma_m = None
    config.execution.scheduler_address = "tcp://127.0.0.1:8786"
    config.advanced.solver.hierarchical_cost_tolerance = 1e-7
    config.advanced.covariance.noise_model = "plane"
    text = dump_config(config)
    assert yaml.safe_load(text)["advanced"]["quality"]["entropy_radius_m"] == 0.3  # every key, unchanged ones too
    assert PaConfig.model_validate(yaml.safe_load(text)) == config


def test_help_points_to_presets_and_config_show(run_pa, monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")  # no wrapping in the help text
    for command in ("refine", "calibrate", "adjust"):
        code, out, _ = run_pa(command, "--help")
        assert code == 0 and "indoor|outdoor|PATH" in out and "pa config show" in out, command
        assert "configs/" not in out
    code, out, _ = run_pa("--help")
    assert "config" in out


# ------------------------------------------------------------------------------------------------ units, docs


def test_every_user_facing_key_has_a_unit_or_is_unitless_by_nature_and_a_description():
    for name in USER_SECTIONS:
        for key, field in type(getattr(PaConfig(), name)).model_fields.items():
            number = field.annotation in (float, float | None)
            assert unit_of(key) or not number, f"{name}.{key}: a quantity without a unit in its name"
            assert len((field.description or "").split()) >= 5, f"{name}.{key}: no description"
    assert sum(len(type(getattr(PaConfig(), name)).model_fields) for name in USER_SECTIONS) <= 30


def test_every_advanced_key_has_a_description():
    advanced = PaConfig().advanced
    for name in type(advanced).model_fields:
        section = type(getattr(advanced, name))
        assert (section.__doc__ or "").strip(), name
        for key, field in section.model_fields.items():
            assert (field.description or "").strip(), f"advanced.{name}.{key}"


def test_docs_config_md_is_current():
    assert PAGE.read_text() == render(), "run: PYTHONPATH=. python docs/make_config_reference.py"
