"""The live link to 3D Slicer (OpenIGTLink): conversions, messages, a lost or absent server, the CLI.

A pyigtl ``OpenIGTLinkServer`` on 127.0.0.1 at a free port stands in for Slicer's OpenIGTLinkIF
server. Every wait is bounded, and every server is stopped at the end of its test.
"""

from __future__ import annotations

import json
import logging
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pyigtl
import pytest

from fluoronav.cli.main import main
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.navigation.case.model import CaseView, NavigationCase, write_navigation_case
from fluoronav.navigation.outputs.igtl import (
    DEVICE_NAME_MAX,
    IGTLinkStreamer,
    ascii_text,
    chain_stage_callbacks,
    device_name,
    image_ijk_to_ras,
    parse_address,
    ras_from_lps_transform,
)
from fluoronav.simulation.navigation.loop import SimulatedNavigationConfig, run_simulated_navigation

LOGGER = "fluoronav.navigation.outputs.igtl"
D = np.diag([-1.0, -1.0, 1.0])  # ras_from_lps for points


# --------------------------------------------------------------------------------------------------
# helpers


class _RecordingServer(pyigtl.OpenIGTLinkServer):
    """pyigtl's server, keeping every message it receives in order (pyigtl itself keeps only the
    latest message per device name)."""

    def __init__(self) -> None:
        self.received: list[Any] = []
        self._received_lock = threading.Lock()
        super().__init__(port=0, local_server=True)

    @property
    def bound_port(self) -> int:
        return int(self.server_address[1])

    def _receive_message_from_socket(self, ssocket: socket.socket) -> bool:
        got = bool(super()._receive_message_from_socket(ssocket))
        if got:
            with self.lock_incoming_messages:
                new = list(self.incoming_messages.values())
                self.incoming_messages.clear()
            with self._received_lock:
                self.received.extend(new)
        return got

    def messages(self, kind: str | None = None, name: str | None = None) -> list[Any]:
        with self._received_lock:
            return [
                m
                for m in self.received
                if (kind is None or m.message_type == kind) and (name is None or m.device_name == name)
            ]


@pytest.fixture
def server() -> Iterator[_RecordingServer]:
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    srv = _RecordingServer()
    try:
        yield srv
    finally:
        srv.stop()
        for s, h in handlers.items():  # pyigtl's server installs its own
            signal.signal(s, h)


def _free_port() -> int:
    """A port on 127.0.0.1 that nothing listens on (bound, then released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_until(predicate: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def _rigid(rx_deg: float, rz_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    ax, az = np.radians(rx_deg), np.radians(rz_deg)
    Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    Rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Rx
    T[:3, 3] = t
    return T


def _camera(camera_from_ct: np.ndarray, *, rows: int = 24, cols: int = 32, spacing: float = 0.5) -> Camera:
    K = np.array([[2000.0, 0.0, 15.0], [0.0, 2000.0, 11.5], [0.0, 0.0, 1.0]])
    return Camera(rows=rows, cols=cols, K=K, camera_from_world=camera_from_ct, pixel_spacing_mm=spacing)


def _central_ray_point_ras(camera: Camera) -> np.ndarray:
    """RAS point on the camera's central ray at the detector distance K[0, 0] · spacing."""
    T = camera.camera_from_world
    source_ct = -T[:3, :3].T @ T[:3, 3]
    axis_ct = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    assert camera.pixel_spacing_mm is not None
    return D @ (source_ct + camera.K[0, 0] * camera.pixel_spacing_mm * axis_ct)


def _view(name: str, camera: Camera, seed: int) -> CaseView:
    image = np.random.default_rng(seed).random((camera.rows, camera.cols)).astype(np.float32)
    return CaseView(name, image, camera)


def _registration(views: tuple[CaseView, ...], cameras: tuple[Camera, ...], k: int) -> SimpleNamespace:
    """Stands in for the pipeline's Registration (the attributes the streamer reads)."""
    return SimpleNamespace(
        views=views,
        cameras_ct=cameras,
        ct_from_cm=_rigid(30.0 + k, -20.0, (12.5 + k, -40.25, 310.0)),
        ct_from_femur=_rigid(2.0, 1.0 + k, (0.5, -1.25, 2.0 + k)),
        cm=SimpleNamespace(control_points_deg=np.full(5, 3.0 + k)),
        tip_ct_mm=np.array([1.0, 2.0, 3.0 + k]),
    )


# --------------------------------------------------------------------------------------------------
# pure functions


def test_ras_from_lps_transform_known_answers() -> None:
    T = np.eye(4)
    T[:3, 3] = (1.0, 2.0, 3.0)
    np.testing.assert_allclose(ras_from_lps_transform(T)[:3, 3], [-1.0, -2.0, 3.0])
    np.testing.assert_allclose(ras_from_lps_transform(T)[:3, :3], np.eye(3))
    # a rotation about x turns the other way in RAS; one about z stays as it is
    np.testing.assert_allclose(
        ras_from_lps_transform(_rigid(30.0, 0.0, (0, 0, 0))), _rigid(-30.0, 0.0, (0, 0, 0))
    )
    np.testing.assert_allclose(
        ras_from_lps_transform(_rigid(0.0, 40.0, (0, 0, 0))), _rigid(0.0, 40.0, (0, 0, 0))
    )
    # it maps RAS points as T maps LPS points, and is its own inverse
    T = _rigid(25.0, -70.0, (10.0, -20.0, 30.0))
    p_lps = np.array([3.0, -4.0, 5.0])
    T_ras = ras_from_lps_transform(T)
    np.testing.assert_allclose(T_ras[:3, :3] @ (D @ p_lps) + T_ras[:3, 3], D @ (T[:3, :3] @ p_lps + T[:3, 3]))
    np.testing.assert_allclose(ras_from_lps_transform(T_ras), T)
    with pytest.raises(ValueError, match="shape"):
        ras_from_lps_transform(np.eye(3))


def test_image_ijk_to_ras_known_answer_for_a_camera_at_the_origin() -> None:
    cam = Camera(
        rows=256,
        cols=256,
        K=np.array([[1000.0, 0, 127.5], [0, 1000.0, 127.5], [0, 0, 1]]),
        pixel_spacing_mm=0.5,
    )
    M = image_ijk_to_ras(cam)
    # detector 500 mm from the source; pixel (u, v) at ((u - 127.5) · 0.5, (v - 127.5) · 0.5, 500) LPS
    np.testing.assert_allclose(M @ [127.5, 127.5, 0, 1], [0.0, 0.0, 500.0, 1.0])
    np.testing.assert_allclose(M @ [0, 0, 0, 1], [63.75, 63.75, 500.0, 1.0])
    np.testing.assert_allclose(M[:3, :3], np.diag([-0.5, -0.5, 0.5]))
    assert np.linalg.det(M[:3, :3]) > 0  # right-handed ijk
    no_spacing = Camera(rows=8, cols=8, K=np.array([[100.0, 0, 3.5], [0, 100.0, 3.5], [0, 0, 1]]))
    np.testing.assert_allclose(
        image_ijk_to_ras(no_spacing) @ [3.5, 3.5, 0, 1], [0.0, 0.0, 100.0, 1.0], atol=1e-9
    )


def test_image_ijk_to_ras_puts_each_pixel_on_its_ray_at_the_detector() -> None:
    cam = _camera(_rigid(35.0, 120.0, (5.0, -30.0, 600.0)))
    M = image_ijk_to_ras(cam)
    np.testing.assert_allclose((M @ [15.0, 11.5, 0.0, 1.0])[:3], _central_ray_point_ras(cam), atol=1e-9)
    for u, v in [(0.0, 0.0), (31.0, 0.0), (7.25, 20.5)]:
        p_lps = D @ (M @ [u, v, 0.0, 1.0])[:3]
        p_cam = cam.camera_from_world[:3, :3] @ p_lps + cam.camera_from_world[:3, 3]
        assert p_cam[2] == pytest.approx(2000.0 * 0.5)
        np.testing.assert_allclose((cam.K @ p_cam)[:2] / p_cam[2], [u, v], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(M[:3, :3], axis=0), [0.5, 0.5, 0.5])
    assert np.linalg.det(M[:3, :3]) > 0


def test_address_and_names() -> None:
    assert parse_address("127.0.0.1:18944") == ("127.0.0.1", 18944)
    assert parse_address("[::1]:18944") == ("::1", 18944)
    for bad in ("127.0.0.1", ":18944", "host:port", "host:0", "host:70000", "::1:18944"):
        with pytest.raises(InputError, match="--igtl"):
            parse_address(bad)
    with pytest.raises(InputError, match="--igtl"):
        IGTLinkStreamer("nowhere")
    assert device_name("view0") == "view0"
    assert device_name("AP view (left)/2") == "AP_view__left__2"
    assert len(device_name("x" * 40)) == DEVICE_NAME_MAX
    assert device_name("") == "view"
    assert ascii_text("stage cm → 3° é") == "stage cm -> 3 deg e"
    calls: list[str] = []
    both = chain_stage_callbacks(
        lambda n, e: calls.append(f"a {n} {e}"), None, lambda n, e: calls.append("b")
    )
    assert both is not None
    both("cm", "start")
    assert calls == ["a cm start", "b"]
    assert chain_stage_callbacks(None, None) is None


# --------------------------------------------------------------------------------------------------
# streaming to a server


def test_streams_images_transforms_and_status(server: _RecordingServer) -> None:
    first = (
        _view("view0", _camera(_rigid(90.0, 0.0, (0.0, 20.0, 500.0))), 0),
        _view("AP view (left side, long name)", _camera(_rigid(90.0, 30.0, (4.0, 20.0, 520.0))), 1),
    )
    registered = tuple(_camera(_rigid(88.0, 3.0 + 30.0 * k, (1.0, 21.0, 505.0 + k))) for k in range(2))
    verify = (_view("verify0", _camera(_rigid(60.0, 10.0, (0.0, 0.0, 480.0)), rows=16, cols=20), 2),)
    reg0 = _registration(first, registered, 0)
    reg1 = _registration(verify, (verify[0].camera,), 1)
    femur_from_cm_target = _rigid(-10.0, 5.0, (20.0, 0.0, -20.0))
    reason = "stage verify_cm, view verify0, check edge_ncc: 0.12 < 0.3 → refused"

    with IGTLinkStreamer(f"127.0.0.1:{server.bound_port}", timeout_s=5.0) as link:
        assert link.connected
        link.on_stage("detect", "start")
        link.on_event("views", {"prefix": "", "views": first})
        link.on_stage("detect", "done")
        link.on_event("registration", {"prefix": "", "registration": reg0})
        link.on_event(
            "plan",
            {"plan": None, "ct_from_femur": reg0.ct_from_femur, "femur_from_cm_target": femur_from_cm_target},
        )
        link.on_event("views", {"prefix": "verify_", "views": verify})
        link.on_event("registration", {"prefix": "verify_", "registration": reg1})
        link.on_event("unknown kind", {})
        link.on_event("status", {"status": "refused", "reason": reason})
    assert not link.connected

    expected_count = 3 + 5 + 3 + 3  # images, transforms, status strings
    assert _wait_until(lambda: len(server.messages()) >= expected_count), [
        (m.message_type, m.device_name) for m in server.messages()
    ]

    # transforms: every one the RAS form of what was sent, to float32 (the wire format)
    sent = [
        ("CMToCT", reg0.ct_from_cm),
        ("FemurToCT", reg0.ct_from_femur),
        ("PlanToCT", reg0.ct_from_femur @ femur_from_cm_target),
        ("CMToCT", reg1.ct_from_cm),
        ("FemurToCT", reg1.ct_from_femur),
    ]
    got = server.messages("TRANSFORM")
    assert [m.device_name for m in got] == [name for name, _ in sent]
    for m, (_, T) in zip(got, sent, strict=True):
        expected = ras_from_lps_transform(T).astype(np.float32).astype(np.float64)
        np.testing.assert_allclose(m.matrix, expected, rtol=0.0, atol=1e-6)
        np.testing.assert_allclose(m.matrix, ras_from_lps_transform(T), rtol=0.0, atol=1e-4)

    # images: per view, the initial camera's placement, then the registered camera's
    names = [m.device_name for m in server.messages("IMAGE")]
    long_name = device_name("AP view (left side, long name)")
    assert names == ["view0", long_name, "view0", long_name, "verify0", "verify0"]
    placements = [
        ("view0", first[0], [first[0].camera, registered[0]]),
        (long_name, first[1], [first[1].camera, registered[1]]),
        ("verify0", verify[0], [verify[0].camera, verify[0].camera]),
    ]
    for name, view, cameras in placements:
        msgs = server.messages("IMAGE", name)
        for m, cam in zip(msgs, cameras, strict=True):
            assert m.image.shape == (1, view.image.shape[0], view.image.shape[1])
            assert m.image.dtype == np.float32
            np.testing.assert_array_equal(m.image[0], view.image)
            cx, cy = cam.K[0, 2], cam.K[1, 2]
            principal = m.ijk_to_world_matrix @ np.array([cx, cy, 0.0, 1.0])
            np.testing.assert_allclose(principal[:3], _central_ray_point_ras(cam), atol=1e-3)
            np.testing.assert_allclose(m.ijk_to_world_matrix, image_ijk_to_ras(cam), atol=1e-3)

    # status strings, in order, the refusal with its reason (in ASCII)
    texts = [m.string for m in server.messages("STRING", "Status")]
    assert texts == [
        "detect: started",
        "detect: done",
        "navigation refused: stage verify_cm, view verify0, check edge_ncc: 0.12 < 0.3 -> refused",
    ]


def test_ok_status_and_stage_strings(server: _RecordingServer) -> None:
    with IGTLinkStreamer(f"127.0.0.1:{server.bound_port}") as link:
        link.on_stage("pelvis", "start")
        link.on_stage("pelvis", "done")
        link.on_event("status", {"status": "ok", "reason": ""})
    assert _wait_until(lambda: len(server.messages("STRING")) >= 3)
    assert [m.string for m in server.messages("STRING", "Status")] == [
        "pelvis: started",
        "pelvis: done",
        "navigation ok",
    ]


def test_no_server_warns_once_and_every_call_is_a_prompt_no_op(caplog: pytest.LogCaptureFixture) -> None:
    cam = _camera(np.eye(4))
    views = (_view("view0", cam, 0),)
    t0 = time.monotonic()
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        with IGTLinkStreamer(f"127.0.0.1:{_free_port()}", timeout_s=1.0) as link:
            assert not link.connected
            for _ in range(3):
                link.on_stage("detect", "start")
                link.on_event("views", {"prefix": "", "views": views})
                link.on_event("registration", {"prefix": "", "registration": _registration(views, (cam,), 0)})
                link.on_event(
                    "plan", {"plan": None, "ct_from_femur": np.eye(4), "femur_from_cm_target": np.eye(4)}
                )
                link.on_event("status", {"status": "refused", "reason": "no CM"})
                link.on_stage("detect", "done")
        link.close()
    assert time.monotonic() - t0 < 5.0
    warnings = [r for r in caplog.records if r.name == LOGGER and r.levelno == logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert "no OpenIGTLink server answered" in warnings[0].getMessage()


def test_a_lost_connection_warns_once_and_then_does_nothing(
    server: _RecordingServer, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        link = IGTLinkStreamer(f"127.0.0.1:{server.bound_port}", timeout_s=2.0).start()
        link.on_stage("detect", "start")
        assert _wait_until(lambda: len(server.messages()) == 1)
        server.stop()  # the server goes away (Slicer closed)
        t0 = time.monotonic()
        for _ in range(200):
            link.on_stage("detect", "done")
            if not link.connected:
                break
            time.sleep(0.02)
        for _ in range(3):
            link.on_event("status", {"status": "ok", "reason": ""})
        link.close()
        assert time.monotonic() - t0 < 5.0
    assert not link.connected
    warnings = [r for r in caplog.records if r.name == LOGGER and r.levelno == logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert "lost" in warnings[0].getMessage()


# --------------------------------------------------------------------------------------------------
# the command line

HEAD = np.array([14.0, 2.0, -6.0])


def _refusing_case(tmp_path: Path, make_case: Callable[..., NavigationCase]) -> Path:
    """A case whose images hold no CM: it refuses at the detect stage, quickly."""
    return write_navigation_case(make_case(), tmp_path / "case")


def _navigate(case: Path, out: Path, igtl: str) -> int:
    """The command's exit status (``main`` returns on success and raises SystemExit otherwise)."""
    try:
        main(["navigate", str(case), "--out", str(out), "--device", "cpu", "--igtl", igtl])
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


def test_navigate_command_streams_a_refusal_to_the_server(
    tmp_path: Path, server: _RecordingServer, make_no_cm_case: Callable[..., NavigationCase]
) -> None:
    case = _refusing_case(tmp_path, make_no_cm_case)
    assert _navigate(case, tmp_path / "out", f"127.0.0.1:{server.bound_port}") == 3
    assert _wait_until(lambda: any("refused" in m.string for m in server.messages("STRING", "Status")))
    images = server.messages("IMAGE")
    assert [m.device_name for m in images] == ["view0", "view1", "view2"]
    assert all(m.image.shape == (1, 256, 256) for m in images)
    texts = [m.string for m in server.messages("STRING", "Status")]
    assert texts[0] == "preflight: started" and "detect: started" in texts and "detect: done" in texts
    assert texts[-1].startswith("navigation refused: stage detect")
    assert not server.messages("TRANSFORM")  # nothing was registered
    nav = json.loads((tmp_path / "out" / "navigation.json").read_text(encoding="utf-8"))
    assert nav["status"] == "refused"


def test_navigate_command_without_a_server_runs_as_without_the_option(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, make_no_cm_case: Callable[..., NavigationCase]
) -> None:
    case = _refusing_case(tmp_path, make_no_cm_case)
    with caplog.at_level(logging.WARNING, logger=LOGGER):
        code = _navigate(case, tmp_path / "out", f"127.0.0.1:{_free_port()}")
    assert code == 3
    nav = json.loads((tmp_path / "out" / "navigation.json").read_text(encoding="utf-8"))
    assert nav["status"] == "refused" and "check views_with_cm" in nav["reason"]
    assert len([r for r in caplog.records if r.name == LOGGER and r.levelno == logging.WARNING]) == 1


# --------------------------------------------------------------------------------------------------
# the whole pipeline on a small simulated phantom case


@pytest.fixture(scope="module")
def small_phantom_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 384² two-view phantom case as the demo writes it (physics-simulated images, landmarks and
    CM masks given, so that the detector does not run), without verification views: about a minute
    of navigation on two cores."""
    case_dir = tmp_path_factory.mktemp("phantom") / "case"
    run_simulated_navigation(
        SimulatedNavigationConfig(seed=21, image_size=384, orbit_deg=(20.0,), oracle_landmarks=True),
        case_dir=case_dir,
        until="case",
    )
    return case_dir / "navigation.json"


def test_navigate_streams_the_registered_poses_of_a_phantom_case(
    tmp_path: Path, server: _RecordingServer, small_phantom_case: Path
) -> None:
    """`fluoronav navigate CASE --igtl`: every TRANSFORM is navigation.json's pose in RAS, every
    view's IMAGE arrives placed first by its initial and then by its registered camera, and the
    status strings follow the stages to "navigation ok"."""
    out = tmp_path / "out"
    assert _navigate(small_phantom_case, out, f"127.0.0.1:{server.bound_port}") == 0
    assert _wait_until(lambda: any(m.string == "navigation ok" for m in server.messages("STRING")))
    nav = json.loads((out / "navigation.json").read_text(encoding="utf-8"))
    assert nav["status"] == "ok"
    ct_from_cm = np.asarray(nav["ct_from_cm"])
    ct_from_femur = np.asarray(nav["ct_from_femur"])
    plan = ct_from_femur @ np.asarray(nav["femur_from_cm_target"])
    got = server.messages("TRANSFORM")
    assert [m.device_name for m in got] == ["CMToCT", "FemurToCT", "PlanToCT"]
    for m, T in zip(got, (ct_from_cm, ct_from_femur, plan), strict=True):
        # LPS → RAS flips the x and y rows and columns: R_ras = D R D, t_ras = D t
        expected = np.eye(4)
        expected[:3, :3] = D @ T[:3, :3] @ D
        expected[:3, 3] = D @ T[:3, 3]
        np.testing.assert_allclose(m.matrix, expected, rtol=0.0, atol=1e-4)

    case = json.loads(small_phantom_case.read_text(encoding="utf-8"))
    names = [device_name(v["name"]) for v in case["views"]]
    images = server.messages("IMAGE")
    assert [m.device_name for m in images] == names + names
    registered = {device_name(k): np.asarray(v) for k, v in nav["carm_from_ct"].items()}
    for m in images[len(names) :]:
        assert m.image.shape == (1, 384, 384)
        # the registered camera: the source (camera origin) sits on the line through the detector
        # point of the principal pixel along the camera's axis, at the detector distance
        T = registered[m.device_name]
        source_ras = D @ (-T[:3, :3].T @ T[:3, 3])
        axis_ras = D @ (T[:3, :3].T @ np.array([0.0, 0.0, 1.0]))
        ijk = m.ijk_to_world_matrix
        normal = np.cross(ijk[:3, 0], ijk[:3, 1])
        assert abs(abs(normal @ axis_ras) / np.linalg.norm(normal) - 1.0) < 1e-6  # detector ⟂ axis
        assert (ijk[:3, 3] - source_ras) @ axis_ras > 500.0  # the detector lies beyond the patient

    texts = [m.string for m in server.messages("STRING", "Status")]
    for stage in ("detect", "pelvis", "femur", "cm", "plan", "robot"):
        assert f"{stage}: started" in texts and f"{stage}: done" in texts
    assert texts[-1] == "navigation ok"
