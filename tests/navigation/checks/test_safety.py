"""The navigation's check thresholds (``SafetyConfig``): its fields as recorded in navigation.json and
the CM registration's checks they set (the checks themselves: tests/registration/cm/test_checks.py)."""

from __future__ import annotations

import dataclasses

import pytest

from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.config import NavigationConfig
from fluoronav.registration.cm.checks import CMCheckConfig


def test_safety_config_keeps_its_fields_and_defaults() -> None:
    assert dataclasses.asdict(SafetyConfig()) == {
        "cm": {
            "max_landmark_residual_mm": 2.0,
            "min_edge_ncc": 0.7,
            "min_views": 2,
            "max_shape_departure_sigmas": None,
            "shape_search_tolerance_deg": 6.0,
            "shape_search_step_deg": 1.0,
            "min_scale_departure": 0.03,
        },
        "max_motion_tip_mm": 3.0,
        "verify_min_views": 1,
        "max_joint_motion_deg": 30.0,
        "max_move_mm": 200.0,
        "max_move_deg": 90.0,
        "max_correction_mm": 10.0,
        "max_correction_deg": 5.0,
        "max_joint_reading_deg": 0.5,
        "overrule_min_views": 3,
        "overrule_max_landmark_residual_mm": 1.0,
        "consistent_views_max_cost_px": 3.0,
        "detection_check_min_views": 2,
        "max_fbg_departure_sigmas": 4.0,
    }


def test_safety_config_sets_the_cm_checks() -> None:
    s = SafetyConfig(
        cm=CMCheckConfig(max_landmark_residual_mm=1.5, min_edge_ncc=0.6, min_views=3), max_motion_tip_mm=4.0
    )
    assert s.cm_checks() == CMCheckConfig(max_landmark_residual_mm=1.5, min_edge_ncc=0.6, min_views=3)
    # the first registration's shape is checked against the FBG reading, the verification's is not
    first = NavigationConfig(safety=s).view_set_settings(verification=False).cm_checks
    assert first == s.cm_checks(fbg=True) and first.max_shape_departure_sigmas == 4.0
    verify = NavigationConfig(safety=s).view_set_settings(verification=True).cm_checks
    assert verify is not None and verify.max_shape_departure_sigmas is None


def test_a_stated_fbg_accuracy_weights_the_first_shape_prior_only() -> None:
    """With the case's ``fbg_sigma_deg`` the first registration's shape is free within 2 σ of the
    reading, Gaussian walls of σ beyond; without it, and in the verification, the default stays."""
    cfg = NavigationConfig()
    default = cfg.view_set_settings(verification=False).cm
    assert default.control_point_sigma_deg == 0.25 and default.control_point_tolerance_deg == 1.0
    stated = cfg.view_set_settings(verification=False, fbg_sigma_deg=0.085).cm
    assert stated.control_point_sigma_deg == 0.085 and stated.control_point_tolerance_deg == pytest.approx(
        0.17
    )
    verify = cfg.view_set_settings(verification=True, fbg_sigma_deg=0.085).cm
    assert verify.control_point_sigma_deg == 0.25 and verify.control_point_tolerance_deg == 1.0


def test_a_two_view_verification_fused_with_the_kinematics_may_keep_one_view() -> None:
    """Fused with the kinematics a two-view verification's CM stands on one view (as a one-image
    verification does); with three views, or from the images alone, it needs ``min_views``."""
    from fluoronav.navigation.config import VerificationConfig

    s = SafetyConfig(cm=CMCheckConfig(min_views=2), verify_min_views=1)
    nav = NavigationConfig(safety=s)
    two = nav.view_set_settings(verification=True, n_views=2).cm_checks
    three = nav.view_set_settings(verification=True, n_views=3).cm_checks
    first = nav.view_set_settings(verification=False, n_views=2).cm_checks
    alone = NavigationConfig(safety=s, verification=VerificationConfig.reference())
    assert two is not None and two.min_views == 1
    assert three == s.cm_checks() and s.cm_checks().min_views == 2
    assert first == s.cm_checks(fbg=True) and first.min_views == 2
    assert alone.view_set_settings(verification=True, n_views=2).cm_checks == s.cm_checks()


def test_navigation_config_gives_each_registration_its_settings_and_one_device() -> None:
    from fluoronav.navigation.config import VerificationConfig
    from fluoronav.registration.cm import CMRegistrationConfig

    first_cm, verify_cm = (
        CMRegistrationConfig(roi_size_full_px=400),
        CMRegistrationConfig(roi_size_full_px=600),
    )
    cfg = NavigationConfig(
        device="cuda:1",
        views=dataclasses.replace(NavigationConfig().views, cm=first_cm, max_cm_starts=1),
        verification=VerificationConfig(cm=verify_cm),
    )
    first, ver = cfg.view_set_settings(verification=False), cfg.view_set_settings(verification=True)
    assert first.device == ver.device == "cuda:1"
    assert first.cm is first_cm and ver.cm is verify_cm and first.max_cm_starts == 1
    assert first.pelvis is cfg.views.pelvis and first.pelvis_refine is cfg.verification.pelvis_refine
