"""Regenerate configs/*.yaml from the config model (run after changing pa_cli/config.py).

    python configs/regenerate.py

default.yaml holds every default; indoor.yaml and outdoor.yaml hold every key too, with the
overrides below. Each key is commented with its unit from the model's descriptions.
"""

from __future__ import annotations

from pathlib import Path

from pa_cli.config import PaConfig, dump_config

PRESETS = {
    "default": ("defaults of every key (the values `pa` uses when a key is not given)", {}),
    "indoor": ("indoor. Rooms, corridors, halls: short ranges, small planes, fine map", {
        "odometry": {"max_range_m": 30.0, "min_range_m": 0.3, "voxel_size_m": 0.1},
        "planes": {"voxel_size_m": 0.5, "max_normal_uncertainty_deg": 0.25},
        "refine": {"map_voxel_m": 0.05, "hold_registration_voxel_m": 0.25},
    }),
    "outdoor": ("outdoor. Streets and campuses: long ranges, large planes (facades, ground), coarser map", {
        "odometry": {"max_range_m": 100.0, "min_range_m": 2.0},
        "planes": {"voxel_size_m": 1.0},
        "refine": {"map_voxel_m": 0.2},
    }),
}


def main() -> None:
    folder = Path(__file__).resolve().parent
    for name, (title, overrides) in PRESETS.items():
        config = PaConfig.model_validate(overrides)
        (folder / f"{name}.yaml").write_text(dump_config(config, title))


if __name__ == "__main__":
    main()
