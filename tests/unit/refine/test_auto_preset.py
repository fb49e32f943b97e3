"""Without --config, the preset follows the scans: rooms indoor, streets outdoor, said in words."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pa_cli.refine.auto_preset import choose_preset, count_rings
from pa_cli.sources import open_source


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    from pa_cli.simulate import SimOptions, simulate

    root = tmp_path_factory.mktemp("auto_preset")
    simulate(SimOptions(scene="office", scans=6, beams=16, azimuth_steps=512, seed=31), root / "office")
    simulate(SimOptions(scene="town", scans=6, beams=32, azimuth_steps=512, seed=32, motion_distortion=True),
             root / "town")
    return root


@pytest.mark.parametrize(("scene", "preset", "rings", "times"), [("office", "indoor", 16, False),
                                                                 ("town", "outdoor", 32, True)])
def test_the_preset_follows_the_scene(simulated, scene, preset, rings, times):
    source = open_source(simulated / scene / "scans")
    try:
        choice = choose_preset(source)
    finally:
        source.close()
    assert choice.name == preset
    assert (choice.range_m <= 30.0) == (preset == "indoor")
    assert choice.rings == rings and choice.with_times == times
    words = choice.reason()
    assert f"using the {preset} preset" in words and f"about {rings} rings" in words and "--config" in words


def test_rings_are_counted_only_where_the_points_have_them():
    rng = np.random.default_rng(3)
    elevations = np.deg2rad(np.linspace(-15.0, 15.0, 16))
    azimuths = rng.uniform(0, 2 * np.pi, 4000)
    ring = rng.integers(0, 16, 4000)
    ranges = rng.uniform(2.0, 40.0, 4000)
    spinning = np.column_stack([ranges * np.cos(elevations[ring]) * np.cos(azimuths),
                                ranges * np.cos(elevations[ring]) * np.sin(azimuths),
                                ranges * np.sin(elevations[ring])])
    assert count_rings(spinning) == 16
    assert count_rings(rng.uniform(-20, 20, (4000, 3))) == 0  # no ring pattern
    assert count_rings(np.empty((0, 3))) == 0


def test_refine_without_config_says_which_preset_and_records_it(run_pa, simulated, tmp_path):
    code, _, err = run_pa("refine", simulated / "office" / "scans", "--out", tmp_path / "map.ply")
    assert code == 0, err
    assert "no --config: using the indoor preset" in " ".join(err.split())
    report = json.loads((tmp_path / "map_report.json").read_text())
    assert report["input"]["config"] == "indoor (chosen from the scans)"
    assert "voxel_m: 0.05" in (tmp_path / "map_config.yaml").read_text()  # the indoor preset's map voxel
