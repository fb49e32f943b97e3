"""Ray-cast LiDAR sequences with exact ground truth (`pa simulate`).

One module per job:

- `mesh`: labelled triangle meshes (a true plane label per triangle);
- `scenes`: the built-in scenes (office, street, town, blocks, avenue, hall);
- `streetscape`: the optional features of the street scenes (road camber and swell, facade relief
  and gaps, curved cars, planting);
- `vegetation`: scatter volumes (tree crowns, hedges) and the rays' leaf hits in them;
- `sensor`: the smooth closed sensor path and the simulation options (with the realism options);
- `effects`: range-dependent noise, mixed pixels, dropouts;
- `raycast`: casting the beams of a spinning LiDAR (range noise, intensity, optional motion
  distortion and realism) into in-memory scans and sequences;
- `writer`: the `pa simulate` output folder, written atomically;
- `ground_truth`: exact-association plane problems built from the true labels.
"""

from pa_cli.simulate.ground_truth import build_problem_from_labels
from pa_cli.simulate.raycast import SimScan, SimulatedSequence, Simulator, simulate_sequence
from pa_cli.simulate.scenes import (
    MIN_LABEL_FACE_AREA_M2,
    SCENE_PATHS,
    SCENES,
    STREET_SCENES,
    MeshBuilder,
    Scene,
    SceneFeatures,
    SceneMesh,
    make_scene,
)
from pa_cli.simulate.sensor import (
    BEAM_CHOICES,
    DEFAULT_VFOV_DEG,
    REALISM_OFF,
    REALISTIC,
    SCAN_PERIOD_S,
    SensorPath,
    SimOptions,
)
from pa_cli.simulate.writer import check_simulation, simulate

__all__ = [
    "BEAM_CHOICES", "DEFAULT_VFOV_DEG", "MIN_LABEL_FACE_AREA_M2", "REALISM_OFF", "REALISTIC", "SCAN_PERIOD_S",
    "SCENE_PATHS", "SCENES", "STREET_SCENES", "MeshBuilder", "Scene", "SceneFeatures", "SceneMesh", "SensorPath",
    "SimOptions", "SimScan", "SimulatedSequence", "Simulator",
    "build_problem_from_labels", "check_simulation", "make_scene", "simulate",
    "simulate_sequence",
]
