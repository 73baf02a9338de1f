"""Result types of the calibration stage (frozen, numpy float64)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["HandEyeFailure", "HandEyeResult", "TipErrors"]


@dataclass(frozen=True)
class HandEyeResult:
    """A hand-eye calibration.

    Attributes:
        ee_from_marker: (4, 4) X, the tracked body (or CM) frame in the end-effector frame.
        rbase_from_tracker: (4, 4) Y, the tracker frame in the robot base frame. Solved jointly for
            AX = YB; for AX = XB it is the chordal mean of the per-pose estimates given X.
        residual_rotation_deg: (N,) per pose, angle of inv(Y · tracker_from_marker_i) ·
            rbase_from_ee_i · X (identity when the data are consistent).
        residual_translation_mm: (N,) per pose, translation norm of the same transform.
        method: OpenCV method name (TSAI, PARK, HORAUD, ANDREFF, DANIILIDIS, SHAH, LI) or another solver.
        formulation: ``"AX=XB"`` or ``"AX=YB"``.
        n_poses: number of poses used.
    """

    ee_from_marker: np.ndarray
    rbase_from_tracker: np.ndarray
    residual_rotation_deg: np.ndarray
    residual_translation_mm: np.ndarray
    method: str
    formulation: str
    n_poses: int

    @property
    def mean_residual_rotation_deg(self) -> float:
        return float(np.mean(self.residual_rotation_deg))

    @property
    def mean_residual_translation_mm(self) -> float:
        return float(np.mean(self.residual_translation_mm))

    @property
    def ok(self) -> bool:
        return True


@dataclass(frozen=True)
class HandEyeFailure:
    """A hand-eye calibration that could not be solved: too few poses, degenerate motion, solver NaN."""

    reason: str
    method: str = ""
    n_poses: int = 0

    @property
    def ok(self) -> bool:
        return False


@dataclass(frozen=True)
class TipErrors:
    """Distances between two estimates of the same tip point (eq. 9 vs eq. 10 of the paper).

    Attributes:
        per_pose_mm: (N,) Euclidean distances.
    """

    per_pose_mm: np.ndarray

    @property
    def mean_mm(self) -> float:
        return float(np.mean(self.per_pose_mm))

    @property
    def std_mm(self) -> float:
        return float(np.std(self.per_pose_mm))

    @property
    def max_mm(self) -> float:
        return float(np.max(self.per_pose_mm))
