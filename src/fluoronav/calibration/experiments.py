"""Accuracy of the tracker-based hand-eye baselines on simulated data.

Run ``python -m fluoronav.calibration.experiments`` to print the table of docs/validation.md
("Tracker-based baselines"; about half a minute on one core).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from fluoronav.calibration.handeye import (
    AX_XB_METHODS,
    AX_YB_METHODS,
    calibrate_hand_eye,
    calibrate_robot_world_hand_eye,
    simulate_tracker_calibration,
    transform_error,
)
from fluoronav.calibration.results import HandEyeResult
from fluoronav.calibration.tracker import DEFAULT_BODY, OpticalTracker
from fluoronav.geometry import se3
from fluoronav.manipulator.robot import UR10, RobotErrorModel, random_configurations_deg

__all__ = ["HOME_DEG", "tracker_baseline_accuracy"]

# A comfortable UR-10 configuration with the flange pointing down, away from singularities.
HOME_DEG = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
_EE_FROM_MARKER = se3.make(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [20.0, -35.0, 110.0])
_RBASE_FROM_TRACKER = se3.make(Rotation.from_rotvec([0.1, 2.0, -0.4]).as_matrix(), [-300.0, 1500.0, 400.0])


def tracker_baseline_accuracy(
    *,
    marker_sigma_mm: float,
    robot_errors: bool,
    n_poses: int = 60,
    seeds: Sequence[int] = tuple(range(20)),
    spread_deg: float = 20.0,
) -> dict[str, tuple[float, float]]:
    """Mean error of X = ``ee_from_marker`` per OpenCV method over ``seeds``.

    Args:
        marker_sigma_mm: tracker marker noise σ per axis.
        robot_errors: whether the physical robot carries :class:`RobotErrorModel` defaults (DH,
            offset and encoder errors, seeded by each seed) while the data report nominal FK.
        n_poses: poses per calibration (the paper used 60).
        seeds: one calibration per seed.
        spread_deg: joint values uniform in ``HOME_DEG ± spread_deg``.

    Returns:
        method → (mean rotation error deg, mean translation error mm).
    """
    errors: dict[str, list[tuple[float, float]]] = {m: [] for m in (*AX_XB_METHODS, *AX_YB_METHODS)}
    for seed in seeds:
        rng = np.random.default_rng(seed)
        q = random_configurations_deg(n_poses, rng=rng, center_deg=HOME_DEG, spread_deg=spread_deg)
        model = RobotErrorModel(seed=seed) if robot_errors else None
        true_robot = model.true_robot(UR10) if model is not None else UR10
        A, B = simulate_tracker_calibration(
            true_robot,
            UR10,
            q,
            ee_from_marker=_EE_FROM_MARKER,
            rbase_from_tracker=_RBASE_FROM_TRACKER,
            tracker=OpticalTracker(marker_sigma_mm=marker_sigma_mm),
            body=DEFAULT_BODY,
            rng=rng,
            error_model=model,
        )
        for method in errors:
            solve = calibrate_hand_eye if method in AX_XB_METHODS else calibrate_robot_world_hand_eye
            res = solve(A, B, method=method)
            if isinstance(res, HandEyeResult):
                errors[method].append(transform_error(res.ee_from_marker, _EE_FROM_MARKER))
    return {
        m: (float(np.mean([e[0] for e in v])), float(np.mean([e[1] for e in v]))) for m, v in errors.items()
    }


def _main() -> None:
    for robot_errors, sigma in ((False, 0.1), (False, 0.25), (True, 0.0), (True, 0.1)):
        res = tracker_baseline_accuracy(marker_sigma_mm=sigma, robot_errors=robot_errors)
        cells = "; ".join(f"{m} {r:.3f}°/{t:.2f} mm" for m, (r, t) in res.items())
        print(
            f"robot errors {robot_errors}, marker σ {sigma} mm: {cells}"
        )  # script entry point, not library code


if __name__ == "__main__":
    _main()
