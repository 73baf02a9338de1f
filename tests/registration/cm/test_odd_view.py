"""One view's refusal named where leaving out that view, and no other, lets the CM fit the rest."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import torch

import fluoronav.registration.cm.shared_causes as shared_causes
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.geometry.carm import carm_camera, orbit_camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm.checks import CMCheckConfig
from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.odd_view import landmark_miss_mm, name_odd_view
from fluoronav.registration.cm.shared_causes import RefusedCM
from fluoronav.registration.cm.views import CMView

_READING = np.array([2.0, -1.0, 3.0, 0.5, -2.0])


@dataclass
class _Reg:
    """A stand-in CM registration: its landmarks in the world."""

    landmarks_world: np.ndarray


def _scene(shift_px: dict[int, float]) -> tuple[RefusedCM, np.ndarray]:
    """Three views (AP, orbits ±25°) of the CM's A and B projected by hand (``u ~ K (R X + t)``), view
    k's landmarks moved by ``shift_px[k]`` pixels along u; the refused registration and A, B (2, 3)."""
    ab = CMKinematics(CMConfig()).landmarks_cm(torch.as_tensor(_READING, dtype=torch.float64)).numpy()
    pts = se3.apply(se3.make(np.eye(3), [5.0, -3.0, 10.0]), ab)
    ap = carm_camera()
    cams = [ap] + [orbit_camera(ap, angle_deg=a, isocenter_world=np.zeros(3)) for a in (-25.0, 25.0)]
    views, lms = [], []
    for k, c in enumerate(cams):
        h = (c.K @ c.camera_from_world[:3] @ np.c_[pts, np.ones(2)].T).T
        lm = h[:, :2] / h[:, 2:] + np.array([shift_px.get(k, 0.0), 0.0])
        lms.append(lm)
        views.append(CMView(np.zeros((8, 8), np.float32), c, landmarks_px=lm, name=f"v{k}"))
    refused = RegistrationRefused("cm", "landmark_residual", "3.1 mm (at most 2 mm)", view="v0")
    failed = RefusedCM(
        refused, views, lms, [[np.eye(4)]], _READING, CMRegistrationConfig(), CMCheckConfig(), 10
    )
    return failed, pts


def _patched(
    monkeypatch: pytest.MonkeyPatch, pts: np.ndarray, fits_without: set[str]
) -> list[dict[str, Any]]:
    """The registration stood in for: on views that leave out one of ``fits_without`` it passes with
    the CM at the truth ``pts``; otherwise it refuses."""
    calls: list[dict[str, Any]] = []

    def registered(views: Any, lms: Any, tries: Any, diag: Any, **kw: Any) -> _Reg:
        names = {v.name for v in views}
        calls.append({"names": names, **kw})
        if not any(n not in names for n in fits_without):
            raise RegistrationRefused("cm", "edge_ncc", "still no fit", view="v0")
        return _Reg(landmarks_world=pts[None])

    monkeypatch.setattr(shared_causes, "register_cm_checked", registered)
    return calls


def test_the_landmark_miss_is_measured_in_mm_at_the_detector() -> None:
    failed, pts = _scene({1: 20.0})
    reg: Any = _Reg(pts[None])
    assert landmark_miss_mm(reg, failed, 0) == pytest.approx(0.0, abs=1e-9)
    spacing = failed.views[1].camera.pixel_spacing_mm or 0.194
    assert landmark_miss_mm(reg, failed, 1) == pytest.approx(20.0 * spacing, rel=1e-9)


def test_the_one_view_that_the_others_disagree_with_is_named(monkeypatch: pytest.MonkeyPatch) -> None:
    """View v1 shows the CM 20 px off: registered on v0 and v2 alone the CM fits them and misses v1
    by 20 px; without v0 or v2 it fits nothing: v1 is named (check odd_view), every remaining view
    held to its check (min_views = the views left)."""
    failed, pts = _scene({1: 20.0})
    calls = _patched(monkeypatch, pts, {"v1"})
    rec: dict[str, Any] = {}
    out = name_odd_view(failed, rec)
    assert (out.stage, out.check, out.view) == ("cm", "odd_view", "v1")
    assert "re-take it" in out.detail and "landmark_residual" in out.detail
    assert rec["v1"]["fits"] and rec["v1"]["miss_mm"] > 2.0 and not rec["v0"]["fits"]
    assert [c["checks"].min_views for c in calls] == [2, 2, 2]
    assert [c["seed"] for c in calls] == [13, 14, 15]


def test_no_view_is_named_where_two_could_be_or_the_left_out_one_fits(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    failed, pts = _scene({1: 20.0, 2: 20.0})
    _patched(monkeypatch, pts, {"v1", "v2"})  # leaving out either fits the rest and misses it
    assert name_odd_view(failed) is failed.refused
    failed, pts = _scene({1: 5.0})  # 5 px ≈ 1 mm: the left-out view agrees within the threshold
    _patched(monkeypatch, pts, {"v1"})
    rec: dict[str, Any] = {}
    assert name_odd_view(failed, rec) is failed.refused and rec["v1"]["miss_mm"] < 2.0


def test_two_views_or_another_check_are_not_searched(monkeypatch: pytest.MonkeyPatch) -> None:
    failed, pts = _scene({1: 20.0})
    calls = _patched(monkeypatch, pts, {"v1"})
    two = failed.subset([0, 1])
    assert name_odd_view(two) is two.refused
    other = RefusedCM(
        RegistrationRefused("cm", "fbg_shape", "x"), failed.views, failed.landmarks_px, failed.tries,
        _READING, failed.config, failed.checks, 0,
    )  # fmt: skip
    assert name_odd_view(other) is other.refused and not calls
