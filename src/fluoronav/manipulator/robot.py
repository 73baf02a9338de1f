"""Serial robot model from standard DH parameters, with the UR-10 preset, analytic IK and errors.

Frames: ``rbase`` is the robot base frame (DH frame 0), ``ee`` the end-effector (tool flange) frame
(DH frame 6). Joint values ``q`` are in degrees at the interface; DH lengths in mm. Standard
(distal) DH: the transform from frame ``i`` to frame ``i−1`` is ``Rz(θ_i) · Tz(d_i) · Tx(a_i) ·
Rx(α_i)`` with ``θ_i = q_i + theta_offset_i``.

Inverse kinematics for UR-type arms uses the closed form (Hawkins 2013, re-derived in
docs/robot-and-calibration.md): up to 8 branches (shoulder ± × wrist ± × elbow ±), each refined by
damped least squares on this robot's exact forward kinematics, which also makes the IK exact for a
robot whose DH parameters carry calibration errors (where the closed form is only approximate).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav.errors import InputError, read_json_object
from fluoronav.geometry import se3

__all__ = [
    "UR10",
    "DHRow",
    "IKFailure",
    "IKSolution",
    "RobotErrorModel",
    "SerialRobot",
    "load_robot",
    "random_configurations_deg",
    "robot_to_dict",
    "wrap_deg",
]

logger = logging.getLogger(__name__)

# Nominal UR joint axis twists; the closed-form IK assumes this structure.
_UR_ALPHA_DEG = (90.0, 0.0, 0.0, 90.0, -90.0, 0.0)


def wrap_deg(angle_deg: np.ndarray | float) -> np.ndarray:
    """Wrap angles in degrees to (−180, 180]."""
    a = np.asarray(angle_deg, dtype=np.float64)
    return 180.0 - np.mod(180.0 - a, 360.0)


@dataclass(frozen=True)
class DHRow:
    """One standard DH row: ``a_mm`` (along x_i), ``alpha_deg`` (about x_i), ``d_mm`` (along z_{i−1}),
    ``theta_offset_deg`` (added to the joint value about z_{i−1})."""

    a_mm: float
    alpha_deg: float
    d_mm: float
    theta_offset_deg: float = 0.0


@dataclass(frozen=True)
class IKSolution:
    """One inverse-kinematics solution.

    Attributes:
        q_deg: (6,) joint values in degrees.
        branch: (shoulder, wrist, elbow) signs in {+1, −1} of the closed form; (0, 0, 0) for a
            solution found from a seed only.
        position_error_mm: |p(FK(q)) − p_target|.
        rotation_error_deg: geodesic angle between R(FK(q)) and R_target.
    """

    q_deg: np.ndarray
    branch: tuple[int, int, int]
    position_error_mm: float
    rotation_error_deg: float


@dataclass(frozen=True)
class IKFailure:
    """No joint configuration reaches the pose within tolerance; ``reason`` says why."""

    reason: str


@dataclass(frozen=True)
class SerialRobot:
    """A revolute serial robot given by standard DH rows.

    Args:
        dh: DH rows, base to end-effector.
        name: label.
        joint_limits_deg: (lower, upper) per joint; UR arms allow ±360° on every joint.
    """

    dh: tuple[DHRow, ...]
    name: str = "robot"
    joint_limits_deg: tuple[tuple[float, float], ...] = field(default=())

    def __post_init__(self) -> None:
        if not self.joint_limits_deg:
            object.__setattr__(self, "joint_limits_deg", tuple((-360.0, 360.0) for _ in self.dh))
        if len(self.joint_limits_deg) != len(self.dh):
            raise ValueError("joint_limits_deg needs one (lower, upper) pair per DH row")

    @property
    def n_joints(self) -> int:
        return len(self.dh)

    @property
    def a_mm(self) -> np.ndarray:
        return np.array([r.a_mm for r in self.dh])

    @property
    def d_mm(self) -> np.ndarray:
        return np.array([r.d_mm for r in self.dh])

    @property
    def alpha_rad(self) -> np.ndarray:
        return np.deg2rad([r.alpha_deg for r in self.dh])

    @property
    def theta_offset_rad(self) -> np.ndarray:
        return np.deg2rad([r.theta_offset_deg for r in self.dh])

    # ------------------------------------------------------------------ forward kinematics
    def _dh_transforms(self, theta_rad: np.ndarray) -> np.ndarray:
        """(..., n) joint-frame angles θ (offsets included) → (..., n, 4, 4) ``prev_from_i``."""
        ct, st = np.cos(theta_rad), np.sin(theta_rad)
        ca, sa = np.cos(self.alpha_rad), np.sin(self.alpha_rad)
        a, d = self.a_mm, self.d_mm
        T = np.zeros((*theta_rad.shape, 4, 4))
        T[..., 0, 0] = ct
        T[..., 0, 1] = -st * ca
        T[..., 0, 2] = st * sa
        T[..., 0, 3] = a * ct
        T[..., 1, 0] = st
        T[..., 1, 1] = ct * ca
        T[..., 1, 2] = -ct * sa
        T[..., 1, 3] = a * st
        T[..., 2, 1] = sa
        T[..., 2, 2] = ca
        T[..., 2, 3] = d
        T[..., 3, 3] = 1.0
        return T

    def _theta(self, q_deg: np.ndarray) -> np.ndarray:
        q = np.asarray(q_deg, dtype=np.float64)
        if q.shape[-1:] != (self.n_joints,):
            raise ValueError(f"q_deg must have shape (..., {self.n_joints}), got {q.shape}")
        return np.deg2rad(q) + self.theta_offset_rad

    def rbase_from_links(self, q_deg: np.ndarray) -> np.ndarray:
        """(..., n) joint values in degrees → (..., n+1, 4, 4) ``rbase_from_frame_i``, i = 0 … n."""
        A = self._dh_transforms(self._theta(q_deg))
        out = np.empty((*A.shape[:-3], self.n_joints + 1, 4, 4))
        out[..., 0, :, :] = np.eye(4)
        for i in range(self.n_joints):
            out[..., i + 1, :, :] = out[..., i, :, :] @ A[..., i, :, :]
        return out

    def rbase_from_ee(self, q_deg: np.ndarray) -> np.ndarray:
        """Forward kinematics: (..., n) joint values in degrees → (..., 4, 4) ``rbase_from_ee``."""
        return self.rbase_from_links(q_deg)[..., -1, :, :]

    def jacobian(self, q_deg: np.ndarray) -> np.ndarray:
        """Geometric Jacobian in the base frame: (..., n) → (..., 6, n).

        Rows 0–2: end-effector origin velocity in mm per rad; rows 3–5: angular velocity (rad per rad).
        """
        F = self.rbase_from_links(q_deg)
        z = F[..., :-1, :3, 2]  # (..., n, 3) joint axes z_{i−1}
        o = F[..., :-1, :3, 3]
        p = F[..., -1:, :3, 3]
        Jv = np.cross(z, p - o)
        return np.concatenate([np.swapaxes(Jv, -1, -2), np.swapaxes(z, -1, -2)], axis=-2)

    # ------------------------------------------------------------------ inverse kinematics
    def _pose_error(self, T: np.ndarray, target: np.ndarray) -> np.ndarray:
        """(6,) [Δp mm, Δrotvec rad] in the base frame, target minus current."""
        dp = target[:3, 3] - T[:3, 3]
        dw = se3.rotvec(target[:3, :3] @ T[:3, :3].T)
        return np.concatenate([dp, dw])

    def refine_ik(
        self,
        rbase_from_ee_target: np.ndarray,
        q_seed_deg: np.ndarray,
        *,
        max_iterations: int = 100,
        damping_mm: float = 1e-3,
        tol_mm: float = 1e-10,
        tol_rad: float = 1e-13,
    ) -> tuple[np.ndarray, float, float]:
        """Damped least-squares (Levenberg–Marquardt style) refinement from a seed.

        Rotation errors are scaled by a characteristic length (1000 mm) so that position and
        orientation residuals are weighted comparably; ``damping_mm`` is the damping in those units.

        Returns:
            (q_deg (n,), position_error_mm, rotation_error_deg).
        """
        target = se3.as_transform_array(rbase_from_ee_target, "rbase_from_ee_target")
        scale = np.array([1.0, 1.0, 1.0, 1000.0, 1000.0, 1000.0])
        q = np.deg2rad(np.asarray(q_seed_deg, dtype=np.float64)).copy()
        lam = damping_mm
        e = self._pose_error(self.rbase_from_ee(np.rad2deg(q)), target)
        cost = float(np.sum((scale * e) ** 2))
        for _ in range(max_iterations):
            if np.linalg.norm(e[:3]) < tol_mm and np.linalg.norm(e[3:]) < tol_rad:
                break
            J = scale[:, None] * self.jacobian(np.rad2deg(q))
            JJt = J @ J.T
            step = J.T @ np.linalg.solve(JJt + lam**2 * np.eye(6), scale * e)
            q_new = q + step
            e_new = self._pose_error(self.rbase_from_ee(np.rad2deg(q_new)), target)
            cost_new = float(np.sum((scale * e_new) ** 2))
            if cost_new < cost:
                q, e, cost = q_new, e_new, cost_new
                lam = max(lam * 0.3, 1e-9)
            else:
                lam *= 10.0
                if lam > 1e6:
                    break
        return np.rad2deg(q), float(np.linalg.norm(e[:3])), float(np.rad2deg(np.linalg.norm(e[3:])))

    def is_ur_type(self, *, tol_mm: float = 5.0, tol_deg: float = 1.0) -> bool:
        """Whether the closed-form UR IK applies (up to small calibration errors)."""
        if self.n_joints != 6:
            return False
        alpha = np.array([r.alpha_deg for r in self.dh])
        a, d = self.a_mm, self.d_mm
        return bool(
            np.all(np.abs(alpha - _UR_ALPHA_DEG) < tol_deg)
            and np.all(np.abs(a[[0, 3, 4, 5]]) < tol_mm)
            and np.all(np.abs(d[[1, 2]]) < tol_mm)
        )

    def closed_form_ik(
        self, rbase_from_ee_target: np.ndarray
    ) -> list[tuple[np.ndarray, tuple[int, int, int]]]:
        """UR closed form: every valid branch as (q_deg (6,), (shoulder, wrist, elbow) signs).

        Uses this robot's a2, a3, d1, d4, d6 and twists of the nominal UR structure; exact for the
        nominal model, a seed for :meth:`refine_ik` otherwise. Angles wrapped to (−180, 180].
        An empty list means the pose is outside the workspace of the closed form.
        """
        if not self.is_ur_type():
            raise ValueError(f"{self.name}: closed-form IK needs the UR joint structure")
        T = se3.as_transform_array(rbase_from_ee_target, "rbase_from_ee_target")
        a, d = self.a_mm, self.d_mm
        a2, a3, d4, d6 = a[1], a[2], d[3], d[5]
        off = self.theta_offset_rad
        p = T[:3, 3]
        p05 = p - d6 * T[:3, 2]  # wrist centre: origin of DH frame 5
        r = math.hypot(p05[0], p05[1])
        if r < abs(d4) or r == 0.0:
            return []
        psi = math.atan2(p05[1], p05[0])
        phi = math.acos(np.clip(d4 / r, -1.0, 1.0))
        solutions: list[tuple[np.ndarray, tuple[int, int, int]]] = []
        for s_sh in (1, -1):
            th1 = psi + s_sh * phi + math.pi / 2.0
            s1, c1 = math.sin(th1), math.cos(th1)
            c5 = (p[0] * s1 - p[1] * c1 - d4) / d6
            if abs(c5) > 1.0 + 1e-9:
                continue
            T16 = se3.inv(self._single_dh(0, th1)) @ T
            for s_wr in (1, -1):
                th5 = s_wr * math.acos(min(1.0, max(-1.0, c5)))
                # R16 = Rz(θ234) Ry(−θ5) Rz(θ6): its z row is (s5 c6, −s5 s6, c5).
                s5 = math.sin(th5)
                # At the wrist singularity (s5 = 0) only θ6 + θ234 is determined; take θ6 = 0.
                th6 = 0.0 if abs(s5) < 1e-12 else math.atan2(-T16[2, 1] / s5, T16[2, 0] / s5)
                T45 = self._single_dh(4, th5)
                T56 = self._single_dh(5, th6)
                T14 = T16 @ se3.inv(T45 @ T56)
                p13 = (T14 @ np.array([0.0, -d4, 0.0, 1.0]))[:3]
                c3 = (p13[0] ** 2 + p13[1] ** 2 - a2**2 - a3**2) / (2.0 * a2 * a3)
                if abs(c3) > 1.0 + 1e-9:
                    continue
                for s_el in (1, -1):
                    th3 = s_el * math.acos(min(1.0, max(-1.0, c3)))
                    th2 = math.atan2(p13[1], p13[0]) - math.atan2(a3 * math.sin(th3), a2 + a3 * math.cos(th3))
                    T12 = self._single_dh(1, th2)
                    T23 = self._single_dh(2, th3)
                    T34 = se3.inv(T12 @ T23) @ T14
                    th4 = math.atan2(T34[1, 0], T34[0, 0])
                    theta = np.array([th1, th2, th3, th4, th5, th6])
                    q = wrap_deg(np.rad2deg(theta - off))
                    solutions.append((q, (s_sh, s_wr, s_el)))
        return solutions

    def _single_dh(self, i: int, theta_rad: float) -> np.ndarray:
        """DH transform of joint ``i`` (0-based) for the joint-frame angle θ (offset included)."""
        ct, st = math.cos(theta_rad), math.sin(theta_rad)
        row = self.dh[i]
        al = math.radians(row.alpha_deg)
        ca, sa = math.cos(al), math.sin(al)
        return np.array(
            [
                [ct, -st * ca, st * sa, row.a_mm * ct],
                [st, ct * ca, -ct * sa, row.a_mm * st],
                [0.0, sa, ca, row.d_mm],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )

    def _within_limits(self, q_deg: np.ndarray, q_near_deg: np.ndarray) -> np.ndarray | None:
        """Equivalent joint values (mod 360) nearest ``q_near_deg`` that respect the limits."""
        q = q_near_deg + wrap_deg(q_deg - q_near_deg)
        lim = np.asarray(self.joint_limits_deg)
        for j in range(self.n_joints):
            for k in (0.0, -360.0, 360.0):
                if lim[j, 0] - 1e-9 <= q[j] + k <= lim[j, 1] + 1e-9:
                    q[j] += k
                    break
            else:
                return None
        return q

    def inverse_kinematics_all(
        self,
        rbase_from_ee_target: np.ndarray,
        *,
        q_near_deg: np.ndarray | None = None,
        tol_mm: float = 1e-6,
        tol_deg: float = 1e-6,
    ) -> list[IKSolution]:
        """Every closed-form branch, refined on the exact FK, kept if within tolerance and limits.

        Args:
            rbase_from_ee_target: (4, 4) target pose.
            q_near_deg: joint values are expressed (mod 360°) nearest to this; zeros by default.
            tol_mm, tol_deg: acceptance tolerance on the refined pose.
        """
        near = np.zeros(self.n_joints) if q_near_deg is None else np.asarray(q_near_deg, dtype=np.float64)
        out: list[IKSolution] = []
        for q0, branch in self.closed_form_ik(rbase_from_ee_target):
            q, ep, er = self.refine_ik(rbase_from_ee_target, q0)
            if ep > tol_mm or er > tol_deg:
                continue
            ql = self._within_limits(q, near)
            if ql is None:
                continue
            out.append(IKSolution(q_deg=ql, branch=branch, position_error_mm=ep, rotation_error_deg=er))
        return out

    def inverse_kinematics(
        self,
        rbase_from_ee_target: np.ndarray,
        *,
        q_reference_deg: np.ndarray | None = None,
        tol_mm: float = 1e-6,
        tol_deg: float = 1e-6,
    ) -> IKSolution | IKFailure:
        """The solution closest to ``q_reference_deg`` (Euclidean on wrapped joint differences).

        For a non-UR robot, ``q_reference_deg`` is required and serves as the DLS seed.

        Returns:
            :class:`IKSolution`, or :class:`IKFailure` where no configuration reaches the pose.
        """
        target = se3.as_transform_array(rbase_from_ee_target, "rbase_from_ee_target")
        ref = None if q_reference_deg is None else np.asarray(q_reference_deg, dtype=np.float64)
        if self.is_ur_type():
            sols = self.inverse_kinematics_all(target, q_near_deg=ref, tol_mm=tol_mm, tol_deg=tol_deg)
            if not sols:
                if not self.closed_form_ik(target):
                    return IKFailure("unreachable: the pose is outside the arm's workspace")
                return IKFailure("no branch converged to the pose within tolerance and joint limits")
            if ref is None:
                ref = np.zeros(self.n_joints)
            dist = [float(np.linalg.norm(wrap_deg(s.q_deg - ref))) for s in sols]
            return sols[int(np.argmin(dist))]
        if ref is None:
            raise ValueError(f"{self.name}: numeric IK of a non-UR robot needs q_reference_deg as seed")
        q, ep, er = self.refine_ik(target, ref)
        ql = self._within_limits(q, ref)
        if ep > tol_mm or er > tol_deg or ql is None:
            return IKFailure(f"damped least squares did not reach the pose ({ep:.3g} mm, {er:.3g} deg)")
        return IKSolution(q_deg=ql, branch=(0, 0, 0), position_error_mm=ep, rotation_error_deg=er)


def _ur10() -> SerialRobot:
    # Universal Robots' published DH table for the UR10 (CB3), converted from m to mm.
    return SerialRobot(
        dh=(
            DHRow(a_mm=0.0, alpha_deg=90.0, d_mm=127.3),
            DHRow(a_mm=-612.0, alpha_deg=0.0, d_mm=0.0),
            DHRow(a_mm=-572.3, alpha_deg=0.0, d_mm=0.0),
            DHRow(a_mm=0.0, alpha_deg=90.0, d_mm=163.941),
            DHRow(a_mm=0.0, alpha_deg=-90.0, d_mm=115.7),
            DHRow(a_mm=0.0, alpha_deg=0.0, d_mm=92.2),
        ),
        name="UR10",
    )


UR10: SerialRobot = _ur10()

_DH_KEYS = {"name", "dh", "joint_limits_deg"}
_DH_ROW_KEYS = {"a_mm", "alpha_deg", "d_mm", "theta_offset_deg"}


def load_robot(path_or_name: str | Path, *, source: str | Path | None = None) -> SerialRobot:
    """A robot model by name (``"UR10"``, any case) or from a DH file (JSON).

    DH file (standard DH, lengths mm, angles deg; ``theta_offset_deg`` and ``joint_limits_deg``
    optional, limits default to ±360° per joint, ``name`` defaults to the file stem)::

        {"name": "UR10",
         "dh": [{"a_mm": 0.0, "alpha_deg": 90.0, "d_mm": 127.3, "theta_offset_deg": 0.0}, ...],
         "joint_limits_deg": [[-360.0, 360.0], ...]}

    Args:
        path_or_name: ``"UR10"`` or the DH file.
        source: the file or option that names the model, for the message when it is neither.

    Raises:
        InputError: an unknown name, or a DH file that is missing, not JSON, has unknown keys, rows
            that are not objects of finite numbers, or limits that are not one ``[lo, hi]`` (lo < hi)
            pair per row. The message names the file.
    """
    name = str(path_or_name).strip()
    if name.upper() == "UR10":
        return UR10
    p = Path(path_or_name)
    if not p.is_file():
        raise InputError(
            source if source is not None else p,
            f'robot model {name!r} is neither "UR10" nor an existing DH file',
        )
    d = read_json_object(p, what="DH file")
    unknown = sorted(set(d) - _DH_KEYS)
    if unknown:
        raise InputError(p, f"unknown key(s) {unknown}; allowed: {sorted(_DH_KEYS)}")

    def number(value: Any, where: str) -> float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(p, f"{where} must be a finite number, got {value!r}")
        return float(value)

    rows = d.get("dh")
    if not isinstance(rows, list) or not rows:
        raise InputError(p, "'dh' must be a non-empty list of {a_mm, alpha_deg, d_mm, theta_offset_deg?}")
    dh = []
    for i, row in enumerate(rows):
        if not isinstance(row, dict):
            raise InputError(p, f"dh[{i}] must be an object")
        bad = sorted(set(row) - _DH_ROW_KEYS)
        if bad:
            raise InputError(p, f"dh[{i}]: unknown key(s) {bad}; allowed: {sorted(_DH_ROW_KEYS)}")
        for key in ("a_mm", "alpha_deg", "d_mm"):
            if key not in row:
                raise InputError(p, f"dh[{i}]: missing '{key}'")
        dh.append(
            DHRow(
                a_mm=number(row["a_mm"], f"dh[{i}].a_mm"),
                alpha_deg=number(row["alpha_deg"], f"dh[{i}].alpha_deg"),
                d_mm=number(row["d_mm"], f"dh[{i}].d_mm"),
                theta_offset_deg=number(row.get("theta_offset_deg", 0.0), f"dh[{i}].theta_offset_deg"),
            )
        )
    limits: list[tuple[float, float]] = []
    if d.get("joint_limits_deg") is not None:
        lim = d["joint_limits_deg"]
        if not isinstance(lim, list) or len(lim) != len(dh):
            raise InputError(p, f"'joint_limits_deg' must hold one [lo, hi] pair per DH row ({len(dh)})")
        for i, pair in enumerate(lim):
            if not isinstance(pair, list) or len(pair) != 2:
                raise InputError(p, f"joint_limits_deg[{i}] must be [lo, hi]")
            lo = number(pair[0], f"joint_limits_deg[{i}][0]")
            hi = number(pair[1], f"joint_limits_deg[{i}][1]")
            if not lo < hi:
                raise InputError(p, f"joint_limits_deg[{i}]: lower {lo} must be below upper {hi}")
            limits.append((lo, hi))
    robot_name = d.get("name", p.stem)
    if not isinstance(robot_name, str) or not robot_name.strip():
        raise InputError(p, "'name' must be a non-empty string")
    return SerialRobot(dh=tuple(dh), name=robot_name, joint_limits_deg=tuple(limits))


def robot_to_dict(robot: SerialRobot) -> dict[str, Any]:
    """The DH file object of ``robot`` (the format :func:`load_robot` reads)."""
    return {
        "name": robot.name,
        "dh": [
            {
                "a_mm": float(r.a_mm),
                "alpha_deg": float(r.alpha_deg),
                "d_mm": float(r.d_mm),
                "theta_offset_deg": float(r.theta_offset_deg),
            }
            for r in robot.dh
        ],
        "joint_limits_deg": [[float(lo), float(hi)] for lo, hi in robot.joint_limits_deg],
    }


@dataclass(frozen=True)
class RobotErrorModel:
    """Differences between the nominal kinematic model and the physical ("true") robot.

    Defaults are modest residuals after a factory kinematic calibration (rationale in
    docs/robot-and-calibration.md): they move the UR-10 flange by 0.1–0.8 mm (median ≈ 0.4 mm), a
    few times its ±0.1 mm pose repeatability and well below the error of an uncalibrated nominal
    model (several mm).

    Attributes:
        joint_offset_sigma_deg: σ of constant per-joint zero-offset errors (added to θ offsets).
        link_length_sigma_mm: σ of errors added to every DH ``a`` and ``d``.
        twist_sigma_deg: σ of errors added to every DH ``alpha``.
        encoder_noise_sigma_deg: σ of the per-reading difference between the reported joint value
            and where the joint actually is.
        seed: seed of the constant errors (the "true" robot is a deterministic function of it).
    """

    joint_offset_sigma_deg: float = 0.02
    link_length_sigma_mm: float = 0.1
    twist_sigma_deg: float = 0.01
    encoder_noise_sigma_deg: float = 0.005
    seed: int = 0

    def true_robot(self, nominal: SerialRobot) -> SerialRobot:
        """The physical robot: ``nominal`` with seeded DH and joint-offset errors."""
        rng = np.random.default_rng(self.seed)
        n = nominal.n_joints
        da = rng.normal(0.0, self.link_length_sigma_mm, n)
        dd = rng.normal(0.0, self.link_length_sigma_mm, n)
        dal = rng.normal(0.0, self.twist_sigma_deg, n)
        dth = rng.normal(0.0, self.joint_offset_sigma_deg, n)
        rows = tuple(
            DHRow(
                a_mm=r.a_mm + da[i],
                alpha_deg=r.alpha_deg + dal[i],
                d_mm=r.d_mm + dd[i],
                theta_offset_deg=r.theta_offset_deg + dth[i],
            )
            for i, r in enumerate(nominal.dh)
        )
        return replace(nominal, dh=rows, name=f"{nominal.name} (true, seed {self.seed})")

    def actual_joints_deg(self, q_reported_deg: np.ndarray, *, rng: np.random.Generator) -> np.ndarray:
        """Where the joints physically are when the encoders report ``q_reported_deg`` (..., n)."""
        q = np.asarray(q_reported_deg, dtype=np.float64)
        return q + rng.normal(0.0, self.encoder_noise_sigma_deg, q.shape)


def random_configurations_deg(
    n: int,
    *,
    rng: np.random.Generator,
    center_deg: np.ndarray,
    spread_deg: float | np.ndarray = 20.0,
) -> np.ndarray:
    """``n`` joint configurations uniform in ``center ± spread`` (degrees) → (n, 6)."""
    c = np.asarray(center_deg, dtype=np.float64)
    s = np.broadcast_to(np.asarray(spread_deg, dtype=np.float64), c.shape)
    return c + rng.uniform(-1.0, 1.0, (n, c.shape[-1])) * s
