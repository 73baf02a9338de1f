"""The navigation's settings tree (``NavigationConfig``): the registrations get exactly the settings
the copied fields gave them, the shipped reference file is the bench's 0.4.1 reference, and a
site's file reaches the checks."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from fluoronav.errors import InputError
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.commands import CommandMotion, check_first_move
from fluoronav.navigation.config import (
    NavigationConfig,
    VerificationConfig,
    navigation_cm_config,
    shipped_settings,
)
from fluoronav.navigation.result import NavigationRefused, NavigationResult
from fluoronav.navigation.targeting import SweptPath
from fluoronav.registration.bone.presets import PELVIS_LINEARIZED_PRESET, PELVIS_REFINE_PRESET
from fluoronav.registration.cm.checks import CMCheckConfig
from fluoronav.registration.cm.config import CMRegistrationConfig, default_cm_levels, fbg_shape_prior
from fluoronav.registration.view_set import ViewSetSettings
from fluoronav.settings import load_settings, settings_dict


def _settings_before_the_tree(
    *,
    verification: bool,
    local: bool = False,
    n_views: int | None = None,
    fbg_sigma_deg: float | None = None,
    device: str = "cpu",
    fuse_kinematics: bool = True,
) -> ViewSetSettings:
    """What ``NavigationConfig.view_set_settings`` gave with the default settings before the tree
    (git show f2bc7d6:src/fluoronav/navigation/result.py): its body with every field's value."""
    fused_views = n_views if verification and fuse_kinematics else None
    cm = CMRegistrationConfig(levels=default_cm_levels())  # cm / verify_cm None: navigation_cm_config()
    if not verification:
        cm = fbg_shape_prior(cm, fbg_sigma_deg)
    two_fused = fused_views is not None and fused_views <= 2
    return ViewSetSettings(
        local=local,
        device=device,
        pelvis=PELVIS_LINEARIZED_PRESET,
        femur=None,
        pelvis_refine=PELVIS_REFINE_PRESET,
        femur_margin_mm=3.0,
        cm=cm,
        max_cm_starts=2,
        cm_checks=CMCheckConfig(
            max_landmark_residual_mm=2.0,
            min_edge_ncc=0.7,
            min_views=1 if two_fused else 2,
            max_shape_departure_sigmas=None if verification else 4.0,
        ),
    )


def _assert_same(new: ViewSetSettings, old: ViewSetSettings) -> None:
    for f in dataclasses.fields(ViewSetSettings):
        a, b = getattr(new, f.name), getattr(old, f.name)
        assert a == b, f.name
        assert repr(a) == repr(b), f.name  # the levels' names too (not compared by ==)


@pytest.mark.parametrize("verification", [False, True])
@pytest.mark.parametrize("local", [False, True])
@pytest.mark.parametrize("n_views", [None, 1, 2, 3])
@pytest.mark.parametrize("fbg_sigma_deg", [None, 0.085])
def test_each_registration_gets_the_settings_it_got_before_the_tree(
    verification: bool, local: bool, n_views: int | None, fbg_sigma_deg: float | None
) -> None:
    kw = dict(verification=verification, local=local, n_views=n_views, fbg_sigma_deg=fbg_sigma_deg)
    _assert_same(NavigationConfig().view_set_settings(**kw), _settings_before_the_tree(**kw))
    cuda = NavigationConfig(device="cuda:1").view_set_settings(**kw)
    _assert_same(cuda, _settings_before_the_tree(**kw, device="cuda:1"))


def test_the_shipped_reference_is_the_config_the_bench_built() -> None:
    """``reference-0.4.1`` over the bench's device and seed: what bench/navigation.py built by hand
    (the CM's CMA-ES levels for both registrations, ``VerificationConfig.reference()`` of 0.9.0)."""
    base = NavigationConfig(device="cpu", seed=3)
    loaded = shipped_settings("reference-0.4.1", base)
    built = dataclasses.replace(
        base,
        views=dataclasses.replace(base.views, cm=CMRegistrationConfig(levels=default_cm_levels())),
        verification=VerificationConfig(
            fuse_kinematics=False, local_bones=False, cm=CMRegistrationConfig(levels=default_cm_levels())
        ),
    )
    assert loaded == built and repr(loaded) == repr(built)
    assert VerificationConfig.reference() == built.verification
    for n_views in (2, 3):
        for verification in (False, True):
            kw = dict(verification=verification, n_views=n_views)
            before = _settings_before_the_tree(**kw, fuse_kinematics=False)
            _assert_same(loaded.view_set_settings(**kw), before)
    assert navigation_cm_config() == CMRegistrationConfig(levels=default_cm_levels())


def test_the_bench_loads_its_reference_from_the_shipped_file() -> None:
    from fluoronav.bench import navigation as bench

    assert bench.REFERENCE_SETTINGS == "reference-0.4.1"
    assert "shipped_settings(REFERENCE_SETTINGS" in Path(bench.__file__).read_text(encoding="utf-8")


def test_safety_contains_the_cm_checks_rather_than_mirroring_them() -> None:
    s = SafetyConfig()
    assert s.cm == CMCheckConfig() and not hasattr(s, "min_edge_ncc")
    assert s.cm_checks(fbg=True) == dataclasses.replace(CMCheckConfig(), max_shape_departure_sigmas=4.0)


def _first_move(joint_deg: float) -> CommandMotion:
    return CommandMotion(
        joint_motion_deg=np.array([0.5, joint_deg, 0.0, 0.0, 0.0, 0.0]),
        swept=SweptPath(20.0, 20.0, 0.0, np.zeros((2, 3))),
        tip_move_mm=20.0,
        rotation_deg=3.0,
    )


def test_a_site_file_bounding_the_joint_motion_makes_the_first_move_refuse(tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text("safety.max_joint_motion_deg = 1\n", encoding="utf-8")
    cfg = load_settings(NavigationConfig(), site)
    assert cfg.safety.max_joint_motion_deg == 1.0
    assert dataclasses.replace(cfg, safety=SafetyConfig()) == NavigationConfig()  # nothing else changed
    check_first_move(_first_move(5.0), NavigationConfig().safety, plan_name="entry")  # the default passes
    with pytest.raises(NavigationRefused) as info:
        check_first_move(_first_move(5.0), cfg.safety, plan_name="entry")
    assert info.value.check == "joint_motion"
    assert "joint 2 by 5.0°, more than the bound 1° (max_joint_motion_deg)" in str(info.value)


def test_a_misspelled_key_is_one_line_naming_the_file_and_the_key(tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text("[safety]\nmax_jont_motion_deg = 20\n", encoding="utf-8")
    with pytest.raises(InputError) as info:
        load_settings(NavigationConfig(), site)
    assert str(info.value) == (
        f"{site}: key safety.max_jont_motion_deg: unknown setting (did you mean safety.max_joint_motion_deg?)"
    )


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ('views.device = "cuda"', "key views.device: not a site setting"),
        ("seed = 3", "key seed: not a site setting (a run's own option"),
        ("views.cm_checks.min_views = 1", "key views.cm_checks: not a site setting (set from safety)"),
        (
            "safety.cm.min_edge_ncc = 1.5",
            "key safety.cm.min_edge_ncc: 1.5 is out of range (must be at most 1)",
        ),
        ("min_views = 1", "key min_views: 1 is out of range (must be at least 2)"),
    ],
)
def test_settings_the_pipeline_sets_or_out_of_range_are_refused(
    tmp_path: Path, text: str, words: str
) -> None:
    site = tmp_path / "site.toml"
    site.write_text(text + "\n", encoding="utf-8")
    with pytest.raises(InputError) as info:
        load_settings(NavigationConfig(), site)
    assert words in str(info.value) and len(str(info.value).splitlines()) == 1


def test_navigation_json_records_the_settings_in_force() -> None:
    cfg = dataclasses.replace(NavigationConfig(), safety=SafetyConfig(max_joint_motion_deg=20.0))
    d = NavigationResult(config=cfg).to_json()
    assert "config" not in d and d["settings"] == settings_dict(cfg)
    assert d["settings"]["safety"]["max_joint_motion_deg"] == 20.0 and d["settings"]["device"] == "cpu"
    assert "device" not in d["settings"]["views"]  # the pipeline's, not the file's
    json.dumps(d, allow_nan=False)
