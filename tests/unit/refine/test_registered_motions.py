"""The odometry factors of `pa refine`: registered motions with the registrations' measured noise."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from pa_cli.config import PaConfig
from pa_cli.refine import rounds
from pa_cli.simulate import SimOptions, simulate_sequence


class _Scans:
    """A scan source over points held in memory."""

    name = "simulated"

    def __init__(self, points: list[np.ndarray]) -> None:
        self._points = points

    def __len__(self) -> int:
        return len(self._points)

    def points(self, k: int) -> np.ndarray:
        return self._points[k]


@contextmanager
def _stage(name: str, total: int | None = None):
    yield lambda done, of: None


def test_registered_pairs_take_the_measured_noise_and_the_others_the_model(monkeypatch):
    """A street of 16 scans whose scan 8 came back empty: pairs 7-8 and 8-9 do not register and keep the start's
    motion with the odometry model's sigmas; every other pair takes the registrations' noise measured on
    closures, per axis, far below the model's."""
    seq = simulate_sequence(SimOptions(scene="street", scans=16, beams=16, realistic=True, seed=917))
    points = [scan.points_scan for scan in seq.scans]
    points[8] = np.zeros((0, 3))
    monkeypatch.setattr(rounds, "pair_scans", lambda *args: None)
    factors, noise = rounds.registered_motions(_Scans(points), None, None, seq.T_world_scan, PaConfig(), _stage)
    assert noise is not None and noise.n_closures >= 8
    unregistered = [7, 8]
    np.testing.assert_array_equal(factors.sigmas[unregistered], factors.model_sigmas()[unregistered])
    registered = np.setdiff1d(np.arange(len(points) - 1), unregistered)
    np.testing.assert_array_equal(factors.sigmas[registered], np.tile(noise.sigmas, (len(registered), 1)))
    assert (noise.sigmas < 0.5 * factors.model_sigmas()[0]).all()
    report = noise.report()
    np.testing.assert_allclose(np.deg2rad(report["rotation_sigma_deg"]), noise.sigmas[:3])
    assert report["n_closures"] == noise.n_closures
