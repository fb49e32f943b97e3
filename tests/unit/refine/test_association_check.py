"""The association the cap froze while it moved: the rounds did not settle, the moves set against the pose covariance
(`association_check`)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from pa_cli.evaluation.degeneracy import Degeneracy
from pa_cli.evaluation.quality import assess
from pa_cli.refine.stages import association_check
from pa_cli.refine.state import Assessment, RoundsResult

SIGMA_M = 0.01  # every scan's position 1-sigma, each axis


def _state(change_m: np.ndarray, with_covariance: bool = True) -> SimpleNamespace:
    """A refine state whose rounds improved the map and settled, but whose last fresh association (round 4)
    moved the scans by `change_m` (N, 3) before the cap froze it."""
    n = len(change_m)
    rms = {name: {"initial": 0.02, "refined": 0.01} for name in ("planes_at_initial_poses", "planes_at_refined_poses")}
    quality = assess(rms, None, None, True, 5.0, 0.01)
    assert quality.verdict == "improved"
    moved = np.linalg.norm(change_m, axis=1)
    unsettled = {"round": 4, "max_pose_change_m": float(moved.max()), "settle_m": 0.01,
                 "scans": [{"scan": j, "moved_m": float(moved[j]), "change_m": change_m[j].tolist()}
                           for j in np.argsort(-moved) if moved[j] > 0.01]}
    rounds = RoundsResult(np.tile(np.eye(4), (n, 1, 1)), None, None, None, [], True, [], None, None,
                          Assessment({"settled": True}, Degeneracy(10.0, [], []), quality),
                          unsettled_association=unsettled)
    covariance = SimpleNamespace(position_covariance_m2=lambda: np.tile(SIGMA_M**2 * np.eye(3), (n, 1, 1)))
    return SimpleNamespace(rounds=rounds, covariance=covariance if with_covariance else None)


def test_moves_within_three_sigma_still_leave_the_rounds_unsettled_and_say_how_far_they_went():
    change = np.zeros((5, 3))
    change[1] = [0.02, 0.0, 0.0]  # 2 sigma
    change[3] = [0.0, 0.025, 0.0]  # 2.5 sigma
    rounds = association_check(_state(change))
    assert not rounds.settled and not rounds.assessment.summary["settled"] and not rounds.assessment.quality.settled
    assert rounds.assessment.quality.verdict == "uncertain"
    assert rounds.unsettled_association["within_3_sigma"] and rounds.unsettled_association["max_sigmas"] == 2.5
    reason = rounds.assessment.quality.reasons[0]
    assert reason.startswith("the rounds did not settle")
    assert "every one within 3 sigma of the pose covariance" in reason
    assert "scans 3 (0.025 m), 1 (0.020 m)" in reason


def test_a_move_beyond_three_sigma_unsettles_the_rounds_and_names_the_scan():
    change = np.zeros((5, 3))
    change[1] = [0.02, 0.0, 0.0]
    change[4] = [0.03, 0.03, 0.0]  # 4.2 sigma: beyond sqrt(14.16) = 3.76
    rounds = association_check(_state(change))
    assert not rounds.settled and not rounds.assessment.summary["settled"] and not rounds.assessment.quality.settled
    assert rounds.assessment.quality.verdict == "uncertain"
    assert rounds.unsettled_association["scans_beyond_3_sigma"] == [4]
    reason = rounds.assessment.quality.reasons[0]
    assert reason.startswith("the rounds did not settle") and "scans 4 (0.042 m)" in reason


def test_without_a_covariance_the_frozen_association_is_not_settled():
    change = np.zeros((3, 3))
    change[0] = [0.02, 0.0, 0.0]
    rounds = association_check(_state(change, with_covariance=False))
    assert not rounds.settled and rounds.assessment.quality.verdict == "uncertain"
    assert "no pose covariance" in rounds.assessment.quality.reasons[0]


def test_rounds_whose_association_settled_are_left_as_they_are():
    state = _state(np.zeros((3, 3)))
    state.rounds.unsettled_association = None
    assert association_check(state) is state.rounds
