"""What real streets have and clean boxes lack: the optional features of the street scenes.

`SceneFeatures` (all off by default, and off they change nothing) adds to a street scene:

- a cambered, undulating road: between the kerbs the road is the curved sheet
  z = undulation * sin(2 pi x / 30 m) - camber * (lateral / half width)^2 (the crown at the
  centre line, `camber` lower at the kerbs), label -1; the vehicle rides on it;
- facade relief: every front is pilasters and recessed bays (steps of 0.1-0.5 m) with balconies
  on some bays (slabs and parapets 0.6-1.2 m out, from the second floor up): many nearby
  parallel planes;
- facade gaps: some buildings are left out (never two in a row), open lots of 10-30 m;
- curved cars: the parked cars become rounded bodies of small triangles (superellipsoids,
  label -1) instead of boxes;
- vegetation: on a share of the street's length, trees (a trunk and a scatter crown) and hedges
  (a scatter box) on the sidewalk; their returns move from scan to scan (`vegetation.py`).

Each feature draws from its own fixed random stream, so turning one on leaves the rest of the
scene where it was.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pa_cli.simulate.mesh import MeshBuilder, rot_z
from pa_cli.simulate.vegetation import VegetationBuilder

ROAD_UNDULATION_WAVELENGTH_M = 30.0  # a slow swell along the road, like a worn surface
ROAD_GRID_M = (1.0, 0.5)  # road sheet spacing along x and across: < 0.3 mm off the true surface
RELIEF_DEPTH_M = 0.5  # the deepest recess behind the pilasters' front
RECESS_STEPS_M = (0.1, 0.2, 0.3, 0.4, 0.5)  # how far a bay steps back from the pilasters
FLOOR_HEIGHT_M = 3.0  # balconies every floor from the second floor (4 m) up
FACADE_GAP_PROBABILITY = 0.3  # share of buildings left out (never two in a row)
VEGETATION_SEGMENT_M = 10.0  # the street's length is planted in pieces of this length
# The features' own random streams: fixed, they are part of the scene like its layout (not --seed).
_RELIEF_SEED, _GAPS_SEED, _CARS_SEED, _PLANTING_SEED = 101, 102, 103, 104


@dataclass(frozen=True)
class Road:
    """The road between the kerbs (|y| < half_width_m): crown on the centre line, swell along x."""

    half_width_m: float
    camber_m: float
    undulation_m: float

    def height(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """z (m) of the road surface at world (x, y); across the kerbs it holds the kerb's value."""
        lateral = np.clip(np.abs(np.asarray(y_m, dtype=np.float64)) / self.half_width_m, 0.0, 1.0)
        swell = self.undulation_m * np.sin(2 * np.pi * np.asarray(x_m, dtype=np.float64)
                                           / ROAD_UNDULATION_WAVELENGTH_M)
        return swell - self.camber_m * lateral**2

    @property
    def lowest_m(self) -> float:
        return -(self.camber_m + self.undulation_m)

    def add_to(self, m: MeshBuilder, x0: float, x1: float) -> None:
        x = np.linspace(x0, x1, int(np.ceil((x1 - x0) / ROAD_GRID_M[0])) + 1)
        y = np.linspace(-self.half_width_m, self.half_width_m,
                        int(np.ceil(2 * self.half_width_m / ROAD_GRID_M[1])) + 1)
        xx, yy = np.meshgrid(x, y, indexing="ij")
        m.height_field(x, y, self.height(xx, yy))


@dataclass(frozen=True)
class SceneFeatures:
    """The optional features of a street scene (module docstring); the defaults add nothing."""

    vegetation: float = 0.0  # share of the street's length planted, 0..1
    curved_cars: bool = False
    road_camber_m: float = 0.0
    road_undulation_m: float = 0.0
    facade_relief: bool = False
    facade_gaps: bool = False

    def any(self) -> bool:
        return self != SceneFeatures()

    def road(self, half_width_m: float) -> Road | None:
        """The shaped road, or None for the flat one."""
        if self.road_camber_m == 0 and self.road_undulation_m == 0:
            return None
        return Road(half_width_m, self.road_camber_m, self.road_undulation_m)


class Facades:
    """Builds the buildings of a street: plain boxes, or with relief; some left out with gaps."""

    def __init__(self, m: MeshBuilder, features: SceneFeatures) -> None:
        self._m = m
        self._relief = np.random.default_rng(_RELIEF_SEED) if features.facade_relief else None
        self._gaps = np.random.default_rng(_GAPS_SEED) if features.facade_gaps else None
        self._left_out_last = False

    def place_next(self) -> bool:
        """Whether the next building stands (always, without gaps)."""
        if self._gaps is None:
            return True
        leave_out = bool(self._gaps.uniform() < FACADE_GAP_PROBABILITY) and not self._left_out_last
        self._left_out_last = leave_out
        return not leave_out

    def building(self, x0: float, x1: float, side: int, front_m: float, depth_m: float, height_m: float) -> None:
        """A building from x0 to x1 whose street front is `front_m` from the centre line on `side`."""

        def across(d0: float, d1: float) -> tuple[float, float]:
            y0, y1 = sorted((side * d0, side * d1))
            return y0, y1

        m = self._m
        if self._relief is None:
            y0, y1 = across(front_m, front_m + depth_m)
            m.box((x0, y0, 0.0), (x1, y1, height_m))
            return
        rng = self._relief
        y0, y1 = across(front_m + RELIEF_DEPTH_M, front_m + depth_m)
        m.box((x0, y0, 0.0), (x1, y1, height_m))  # the core behind the deepest recess
        x = x0
        while x1 - x > 0.3:
            b = min(x + float(rng.uniform(0.5, 1.0)), x1)  # a pilaster, flush with the front
            y0, y1 = across(front_m, front_m + RELIEF_DEPTH_M)
            m.box((x, y0, 0.0), (b, y1, height_m))
            x = b
            if x1 - x <= 0.3:
                break
            b = min(x + float(rng.uniform(2.0, 4.0)), x1)
            if x1 - b < 1.0:
                b = x1
            recess = float(rng.choice(RECESS_STEPS_M))
            if recess < RELIEF_DEPTH_M:
                y0, y1 = across(front_m + recess, front_m + RELIEF_DEPTH_M)
                m.box((x, y0, 0.0), (b, y1, height_m))
            if rng.uniform() < 0.4 and b - x > 1.5:  # balconies on this bay
                out = float(rng.uniform(0.6, 1.2))
                for z in np.arange(4.0, height_m - 2.0, FLOOR_HEIGHT_M):
                    y0, y1 = across(front_m - out, front_m + recess)
                    m.box((x + 0.2, y0, z), (b - 0.2, y1, z + 0.15))  # slab
                    y0, y1 = across(front_m - out, front_m - out + 0.05)
                    m.box((x + 0.2, y0, z + 0.15), (b - 0.2, y1, z + 1.1))  # parapet
            x = b


class Cars:
    """Parked cars: the scene's boxes, or curved bodies when `curved`."""

    def __init__(self, m: MeshBuilder, curved: bool, road: Road | None) -> None:
        self._m = m
        self._rng = np.random.default_rng(_CARS_SEED) if curved else None
        self._road = road

    @property
    def curved(self) -> bool:
        return self._rng is not None

    def curved_car(self, x: float, y: float) -> None:
        """A rounded body and cabin (superellipsoids) on four wheels, slightly askew, on the road."""
        rng = self._rng
        assert rng is not None
        length = float(rng.uniform(3.9, 4.8))
        yaw_deg = float(rng.normal(0.0, 2.0))
        x += float(rng.uniform(-0.4, 0.4))
        z0 = 0.0 if self._road is None else float(self._road.height(np.array(x), np.array(y)))
        R = rot_z(np.deg2rad(yaw_deg))[:2, :2]
        m = self._m
        m.superellipsoid((x, y, z0 + 0.72), (length / 2, 0.88, 0.42), exponent=0.35, yaw_deg=yaw_deg)
        cx, cy = np.array([x, y]) + R @ [-0.15, 0.0]
        m.superellipsoid((float(cx), float(cy), z0 + 1.12), (0.26 * length, 0.76, 0.34), exponent=0.6,
                         yaw_deg=yaw_deg)
        for sx in (-0.32 * length, 0.32 * length):
            for sy in (-0.8, 0.8):
                wx, wy = np.array([x, y]) + R @ [sx, sy]
                m.cylinder((float(wx), float(wy)), 0.3, z0, z0 + 0.32, resolution=8)


def plant_street(m: MeshBuilder, fraction: float, x0: float, x1: float, tree_m: float,
                 hedge_m: tuple[float, float], sidewalk_top_m: float) -> VegetationBuilder:
    """Trees and hedges on `fraction` of the pieces of the street from x0 to x1, both sides.

    Trees stand `tree_m` from the centre line (trunk in the mesh, crown a scatter ellipsoid);
    hedges run between `hedge_m` (distances from the centre line) on the sidewalk.
    """
    rng = np.random.default_rng(_PLANTING_SEED)
    veg = VegetationBuilder()
    starts = np.arange(x0, x1, VEGETATION_SEGMENT_M)
    for side in (-1, 1):
        planted = np.sort(rng.permutation(len(starts))[:int(round(fraction * len(starts)))])
        for start in starts[planted]:
            tree, hedge = rng.uniform(size=2)
            tx = float(start + rng.uniform(3.0, 7.0))
            trunk_r = float(rng.uniform(0.12, 0.25))
            semi = (float(rng.uniform(1.8, 3.0)), float(rng.uniform(1.5, 2.2)), float(rng.uniform(1.4, 2.4)))
            crown_z = sidewalk_top_m + float(rng.uniform(2.3, 3.2)) + 0.85 * semi[2]
            hedge_h = float(rng.uniform(0.9, 1.6))
            if tree < 0.75:
                m.cylinder((tx, side * tree_m), trunk_r, sidewalk_top_m, crown_z, resolution=10)
                veg.crown((tx, side * tree_m, crown_z), semi)
            if hedge < 0.6 or tree >= 0.75:
                ya, yb = sorted((side * hedge_m[0], side * hedge_m[1]))
                seg_end = float(min(start + VEGETATION_SEGMENT_M, x1))
                veg.hedge((float(start) + 0.5, ya, sidewalk_top_m), (seg_end - 0.5, yb, sidewalk_top_m + hedge_h))
    return veg
