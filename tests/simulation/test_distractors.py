"""Distractor metal: analytic chords against hand-computed ones, drawing, placement near the CM."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import carm_camera
from fluoronav.simulation.distractors import (
    DISTRACTORS_OFF,
    DISTRACTORS_REALISTIC,
    distractor_densities,
    draw_distractors,
    render_distractors,
    solid_chord_mm,
)
from fluoronav.simulation.materials import MATERIALS

F_PX, Z_MM = 1000.0, 500.0
STEEL_G_CM3 = MATERIALS["stainless_steel"].density_g_cm3


def _camera(n: int = 65) -> Camera:
    """World = camera frame; the principal point on the centre pixel (32, 32)."""
    c = (n - 1) / 2.0
    return Camera(n, n, np.array([[F_PX, 0.0, c], [0.0, F_PX, c], [0.0, 0.0, 1.0]]), np.eye(4))


def _rod(radius_mm: float, inner_mm: float = 0.0) -> dict:
    """A steel tube (solid for ``inner_mm`` 0) along x through (0, 0, Z)."""
    return {
        "kind": "tube",
        "material": "stainless_steel",
        "diameter_mm": 2.0 * radius_mm,
        "inner_diameter_mm": 2.0 * inner_mm,
        "start_world_mm": [-100.0, 0.0, Z_MM],
        "end_world_mm": [100.0, 0.0, Z_MM],
    }


def _half_chord(r: float, d: float) -> float:
    return math.sqrt(max(r * r - d * d, 0.0))


def test_cylinder_areal_density_is_the_hand_computed_chord() -> None:
    r = 1.2
    dens = render_distractors(_camera(), [_rod(r)], oversample=1)["stainless_steel"].double()
    centre = 32
    # the central ray crosses the axis at right angles: 2r
    assert dens[centre, centre].item() == pytest.approx(2.0 * r * STEEL_G_CM3 / 10.0, rel=1e-3)
    # rows off the centre: rays in the y–z plane at distance Z·sin(atan(k/f)) from the axis
    for k in (1, 2, -2):
        d = Z_MM * math.sin(math.atan(k / F_PX))
        expected = 2.0 * _half_chord(r, d) * STEEL_G_CM3 / 10.0
        assert dens[centre + k, centre].item() == pytest.approx(expected, rel=1e-3)
    # columns off the centre: rays through the axis at an angle, 2r / sin(angle to the axis)
    for k in (5, -12):
        expected = 2.0 * r * math.sqrt(1.0 + (k / F_PX) ** 2) * STEEL_G_CM3 / 10.0
        assert dens[centre, centre + k].item() == pytest.approx(expected, rel=1e-3)
    assert dens[centre + 4, centre].item() == 0.0  # d ≈ 2 mm > r: a miss


def test_hollow_tube_and_capsule_chords() -> None:
    r_out, r_in = 1.2, 0.7
    dens = render_distractors(_camera(), [_rod(r_out, r_in)], oversample=1)["stainless_steel"].double()
    for k in (0, 1):
        d = Z_MM * math.sin(math.atan(k / F_PX))
        expected = 2.0 * (_half_chord(r_out, d) - _half_chord(r_in, d)) * STEEL_G_CM3 / 10.0
        assert dens[32 + k, 32].item() == pytest.approx(expected, rel=1e-3)
    # a capsule end-on: the cylinder's length plus the cap's radius
    origin = torch.zeros(3, dtype=torch.float64)
    along = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    chord = solid_chord_mm(origin, along, [0.0, 0.0, 400.0], [0.0, 0.0, 600.0], 1.0, caps=(True, False))
    assert chord.item() == pytest.approx(201.0, rel=1e-9)
    both = solid_chord_mm(origin, along, [0.0, 0.0, 400.0], [0.0, 0.0, 600.0], 1.0, caps=(True, True))
    assert both.item() == pytest.approx(202.0, rel=1e-9)


def test_off_draws_nothing_and_renders_nothing() -> None:
    rng = np.random.default_rng(3)
    before = rng.bit_generator.state
    dens, records = distractor_densities(_camera(), np.zeros(3), DISTRACTORS_OFF, rng)
    assert dens == {} and records == []
    assert rng.bit_generator.state == before


def test_seeded_draws_are_deterministic_and_json_ready() -> None:
    anchor = np.array([10.0, -5.0, 3.0])
    a = draw_distractors(anchor, DISTRACTORS_REALISTIC, np.random.default_rng(11))
    b = draw_distractors(anchor, DISTRACTORS_REALISTIC, np.random.default_rng(11))
    assert a == b and {r["kind"] for r in a} == {"k_wire", "screw", "tube", "cable"}
    for r in a:
        assert r["material"] in MATERIALS
        for v in r.values():
            assert isinstance(v, str | bool | float | list)


def test_objects_pass_near_the_given_cm_points() -> None:
    near = np.array([[0.0, 0.0, 0.0], [30.0, 10.0, -5.0]])
    cfg = dataclasses.replace(DISTRACTORS_REALISTIC, p_near_cm=1.0, cable=False)
    records = draw_distractors(np.full(3, 200.0), cfg, np.random.default_rng(5), near_world_mm=near)
    for r in records:
        a, b = np.asarray(r["start_world_mm"]), np.asarray(r["end_world_mm"])
        ab = b - a
        t = np.clip((near - a) @ ab / (ab @ ab), 0.0, 1.0)
        dist = np.linalg.norm(near - (a + t[:, None] * ab), axis=1).min()
        assert r["near_cm"] and dist <= cfg.near_cm_radius_mm + 1e-9


def test_realistic_distractors_render_at_a_carm_view() -> None:
    camera = carm_camera(lao_rao_deg=20.0, cran_caud_deg=5.0, isocenter_world=np.zeros(3)).scaled_to(128, 128)
    dens, records = distractor_densities(camera, np.zeros(3), DISTRACTORS_REALISTIC, np.random.default_rng(2))
    assert records and set(dens) <= set(MATERIALS)
    for v in dens.values():
        assert v.shape == (128, 128) and v.dtype == torch.float32
        assert torch.isfinite(v).all() and (v >= 0).all()
    assert sum(float(v.sum()) for v in dens.values()) > 0
    # the same records render the same at the same camera (the draws are all in them)
    again = render_distractors(camera, records, oversample=DISTRACTORS_REALISTIC.oversample)
    assert all(torch.equal(again[m], dens[m]) for m in dens)
