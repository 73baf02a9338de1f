"""Shared pytest configuration, and the navigation tests' small case that refuses at detection."""

from __future__ import annotations

import os

# Two cores on CI: keep torch from oversubscribing when numba also runs threads.
os.environ.setdefault("OMP_NUM_THREADS", "2")

from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import settings

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import Camera, DetectorSpec
from fluoronav.geometry.carm import carm_camera_from_world
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.robot import UR10
from fluoronav.navigation.case.model import CaseView, NavigationCase
from fluoronav.navigation.planning import Plan

# CI is deterministic (the same examples every run); HYPOTHESIS_PROFILE=deep searches widely.
settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("deep", max_examples=1500, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

HEAD = np.array([14.0, 2.0, -6.0])
HEAD_RADIUS_MM = 20.0
#: the plan: the CM tip on the head's surface, its axis towards the centre
PLAN_DIRECTION = np.array([-0.7071, 0.0, 0.7071])


def _volume() -> Volume:
    """40³ voxels at 3 mm: a pelvis block (256 mL) and a left femoral head ball (r = 20 mm, 34 mL),
    labelled, each of a size the preflight's label checks find plausible."""
    n, h = 40, 3.0
    origin = -0.5 * h * (n - 1)
    ax = origin + h * np.arange(n)
    Z, Y, X = np.meshgrid(ax, ax, ax, indexing="ij")
    labels = np.zeros((n, n, n), np.uint8)
    labels[(np.abs(X) < 40) & (np.abs(Y) < 40) & (Z > 20)] = 1
    labels[(X - HEAD[0]) ** 2 + (Y - HEAD[1]) ** 2 + (Z - HEAD[2]) ** 2 < HEAD_RADIUS_MM**2] = 2
    return Volume(
        data=np.where(labels > 0, 600.0, -100.0).astype(np.float32),
        spacing_mm=(h, h, h),
        origin_mm=(origin, origin, origin),
        labels=labels,
        label_names={1: "pelvis", 2: "femur_left"},
        landmarks_world={"femoral_head_left": HEAD.copy()},
    )


def no_cm_case(n_views: int = 3, size: int = 256) -> NavigationCase:
    """A case whose images hold no CM (smooth noise): the navigation refuses at its detect stage."""
    rng = np.random.default_rng(0)
    views = []
    for k in range(n_views):
        T = carm_camera_from_world(
            lao_rao_deg=20.0 * k, cran_caud_deg=90.0, source_to_isocenter_mm=450.0, isocenter_world=HEAD
        )
        cam = Camera.from_detector(
            DetectorSpec(rows=size, cols=size, pixel_spacing_mm=1.164, sdd_mm=1020.0), T
        )
        image = (0.5 + 0.05 * rng.standard_normal((size, size))).astype(np.float32)
        views.append(CaseView(f"view{k}", image, cam))
    return NavigationCase(
        volume=_volume(),
        plan=Plan("entry", HEAD - HEAD_RADIUS_MM * PLAN_DIRECTION, PLAN_DIRECTION),
        side="left",
        cm_config=CMConfig(),
        fbg_control_points_deg=np.zeros(5),
        robot=UR10,
        joints_deg=np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0]),
        ee_from_cm=np.eye(4),
        views=tuple(views),
    )


@pytest.fixture
def make_no_cm_case() -> Callable[..., NavigationCase]:
    """:func:`no_cm_case` as a fixture (test modules do not import each other)."""
    return no_cm_case
