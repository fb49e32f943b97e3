"""Trajectory evaluation: alignment, timestamp association, ATE / RPE, and the perturbation model.

One module per job: `alignment` (Umeyama, alignment modes), `association` (pairing poses by
timestamp or index), `metrics` (ATE and RPE, defined as evo's `evo_ape` / `evo_rpe`) and
`perturbation` (the pose noise model of the plane-adjustment papers, `pa perturb`).
"""

from pa_cli.evaluation.alignment import (
    ALIGN_MODES,
    AlignMode,
    alignment_transform,
    apply_alignment,
    rotation_alignment_note,
    umeyama_alignment,
)
from pa_cli.evaluation.association import (
    MIN_PAIRED_FRACTION,
    WARN_PAIRED_FRACTION,
    match_timestamps,
    pair_trajectories,
)
from pa_cli.evaluation.metrics import PoseErrors, evaluate, pose_errors
from pa_cli.evaluation.perturbation import PERTURBATION_LEVELS, perturb_poses

__all__ = [
    "ALIGN_MODES", "MIN_PAIRED_FRACTION", "PERTURBATION_LEVELS", "WARN_PAIRED_FRACTION", "AlignMode", "PoseErrors",
    "alignment_transform", "apply_alignment", "evaluate", "match_timestamps", "pair_trajectories",
    "perturb_poses", "pose_errors", "rotation_alignment_note", "umeyama_alignment",
]
