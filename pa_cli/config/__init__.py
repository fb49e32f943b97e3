"""Every tunable of `pa`, with its unit and the reason it exists.

`model`: the sections (`PaConfig`: sensor, scene, refine, loops, map, execution, advanced);
`load`: presets and files in, commented YAML out (`load_config`, `dump_config`); `renamed`: where
every key of pa 0.1 went. `pa config show [PRESET|PATH]` prints the effective config; the
presets ship in pa_cli/presets.
"""

from pa_cli.config.load import dotted_keys, dump_config, load_config, preset_names
from pa_cli.config.model import (
    USER_SECTIONS,
    AdvancedConfig,
    AdvancedExecutionConfig,
    AdvancedPlanesConfig,
    AssociationConfig,
    CalibrateConfig,
    CovarianceConfig,
    DegeneracyConfig,
    DeskewConfig,
    EdgesConfig,
    ExecutionConfig,
    KissIcpConfig,
    LoopClosureConfig,
    LoopsConfig,
    MapConfig,
    OdometryConfig,
    PaConfig,
    PlanesConfig,
    QualityConfig,
    RefineConfig,
    RegistrationConfig,
    SceneConfig,
    SensorConfig,
    SolverConfig,
)
from pa_cli.config.renamed import CONSTANTS, REMOVED, RENAMED, RENAMED_IN

__all__ = [
    "CONSTANTS", "REMOVED", "RENAMED", "RENAMED_IN", "USER_SECTIONS", "AdvancedConfig", "AdvancedExecutionConfig",
    "AdvancedPlanesConfig", "AssociationConfig", "CalibrateConfig", "CovarianceConfig", "DegeneracyConfig",
    "DeskewConfig", "EdgesConfig", "ExecutionConfig", "KissIcpConfig", "LoopClosureConfig", "LoopsConfig",
    "MapConfig", "OdometryConfig", "PaConfig", "PlanesConfig", "QualityConfig", "RefineConfig", "RegistrationConfig",
    "SceneConfig", "SensorConfig", "SolverConfig", "dotted_keys", "dump_config", "load_config", "preset_names",
]
