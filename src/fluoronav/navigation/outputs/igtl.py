"""The navigation, live in 3D Slicer over OpenIGTLink (``fluoronav navigate --igtl HOST:PORT``).

:class:`IGTLinkStreamer` is an OpenIGTLink client of 3D Slicer's OpenIGTLinkIF server. It takes the pipeline's
callbacks (``on_stage``, ``on_event``: :data:`fluoronav.navigation.pipeline.EventCallback`) and sends each
result as soon as it is known: STRING ``Status``, an IMAGE per view (the detector plane in the CT,
:func:`image_ijk_to_ras`, named by :func:`device_name`) and the TRANSFORMs ``CMToCT``, ``FemurToCT`` and
``PlanToCT`` (docs/navigation.md, "Live view in 3D Slicer"). Slicer's scene is RAS, the CT frame LPS: every
pose and image geometry is sent in RAS (:func:`ras_from_lps_transform`), a TRANSFORM as its node's "to parent"
matrix. The link never changes the navigation: if no server answers within ``timeout_s`` at the start, or the
connection is lost, the streamer logs one warning and does nothing more. Each message is sent synchronously
(bounded by ``timeout_s``), in the order the pipeline reports.
"""

from __future__ import annotations

import logging
import re
import select
import socket
import threading
import unicodedata
from collections.abc import Callable, Mapping
from types import TracebackType
from typing import TYPE_CHECKING, Any, Self

import numpy as np
import pyigtl

from fluoronav.errors import InputError

if TYPE_CHECKING:
    from fluoronav.geometry.camera import Camera

__all__ = [
    "DEVICE_NAME_MAX",
    "RAS_FROM_LPS",
    "IGTLinkStreamer",
    "ascii_text",
    "chain_stage_callbacks",
    "device_name",
    "image_ijk_to_ras",
    "parse_address",
    "ras_from_lps_transform",
]

log = logging.getLogger(__name__)

#: (4, 4) the LPS → RAS change of coordinates (its own inverse)
RAS_FROM_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])
#: the OpenIGTLink header's device-name field, bytes
DEVICE_NAME_MAX = 20

StageCallback = Callable[[str, str], None]

_UNSAFE_NAME_CHARS = re.compile(r"[^A-Za-z0-9_.-]")
_ASCII_SPELLING = {"→": "->", "←": "<-", "°": " deg", "±": "+/-", "×": "x", "≤": "<=", "≥": ">=", "²": "2"}


# --------------------------------------------------------------------------------------------------
# pure conversions


def parse_address(address: str) -> tuple[str, int]:
    """``"HOST:PORT"`` (or ``"[IPv6]:PORT"``) → (host, port).

    Raises:
        InputError: (source ``--igtl``) not of that form, or the port is not in 1..65535.
    """
    text = str(address).strip()
    host, sep, port_text = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or (":" in host and not text.startswith("[")):
        raise InputError("--igtl", f"expected HOST:PORT (e.g. 127.0.0.1:18944), got {text!r}")
    if not port_text.isdigit() or not 1 <= int(port_text) <= 65535:
        raise InputError("--igtl", f"the port must be a number in 1..65535, got {port_text!r}")
    return host, int(port_text)


def ras_from_lps_transform(T: np.ndarray) -> np.ndarray:
    """A transform between LPS frames, expressed between the same frames in RAS.

    Args:
        T: (4, 4) ``a_from_b`` with both a and b in LPS coordinates (mm).

    Returns:
        (4, 4) float64 ``ras_from_lps @ T @ lps_from_ras``: the same map for points given and
        returned in RAS (x and y negated), as Slicer's transform nodes hold it. E.g. a translation
        (tx, ty, tz) becomes (-tx, -ty, tz); a rotation by θ about x becomes one by -θ about x, one
        about z stays as it is.
    """
    M = np.asarray(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"a transform must have shape (4, 4), got {M.shape}")
    return RAS_FROM_LPS @ M @ RAS_FROM_LPS


def image_ijk_to_ras(camera: Camera) -> np.ndarray:
    """Where Slicer should place a view's image: the detector plane of its C-arm in the CT, in RAS.

    In the camera frame (OpenCV pinhole: origin at the X-ray source, +z towards the detector) the
    detector is the plane ``z = d`` with ``d = K[0, 0] · s`` mm, ``s`` the detector pixel spacing
    (``camera.pixel_spacing_mm``; 1 mm when the camera does not give it, which keeps the geometry
    but not the size). Pixel (u, v) lies on its ray at that plane: ``d · K⁻¹ (u, v, 1)``, i.e.
    ``((u - cx) · s, (v - cy) · s, f · s)`` for square pixels without skew. The image is one slice
    (k = 0) whose k axis points along +z (thickness ``s``), so the ijk frame is right-handed.

    Args:
        camera: ``K`` (3, 3) pixels, ``camera_from_world`` (4, 4) = ``camera_from_ct`` (LPS, mm).

    Returns:
        (4, 4) float64 ``ras_from_ijk`` with i = column u, j = row v, k = slice: ``ras_from_lps @
        inv(camera_from_ct) @ camera_from_ijk``.
    """
    K = np.asarray(camera.K, dtype=np.float64)
    s = float(camera.pixel_spacing_mm) if camera.pixel_spacing_mm else 1.0
    d = float(K[0, 0]) * s
    K_inv = np.linalg.inv(K)
    camera_from_ijk = np.eye(4)
    camera_from_ijk[:3, 0] = d * K_inv[:, 0]
    camera_from_ijk[:3, 1] = d * K_inv[:, 1]
    camera_from_ijk[:3, 2] = (0.0, 0.0, s)
    camera_from_ijk[:3, 3] = d * K_inv[:, 2]
    camera_from_ct = np.asarray(camera.camera_from_world, dtype=np.float64)
    R, t = camera_from_ct[:3, :3], camera_from_ct[:3, 3]
    ct_from_camera = np.eye(4)
    ct_from_camera[:3, :3] = R.T
    ct_from_camera[:3, 3] = -R.T @ t
    return RAS_FROM_LPS @ ct_from_camera @ camera_from_ijk


def device_name(name: str) -> str:
    """An OpenIGTLink device name for ``name``: characters other than letters, digits, ``_``, ``.``
    and ``-`` become ``_``, at most :data:`DEVICE_NAME_MAX` of them (``"view"`` if none is left)."""
    return _UNSAFE_NAME_CHARS.sub("_", str(name))[:DEVICE_NAME_MAX] or "view"


def ascii_text(text: str) -> str:
    """``text`` in ASCII for a STRING message (common symbols spelled out, others as ``?``)."""
    spelled = unicodedata.normalize("NFKD", "".join(_ASCII_SPELLING.get(c, c) for c in str(text)))
    plain = "".join(c for c in spelled if not unicodedata.combining(c))
    return plain.encode("ascii", "replace").decode("ascii")


def chain_stage_callbacks(*callbacks: StageCallback | None) -> StageCallback | None:
    """One ``on_stage`` callback calling each of ``callbacks`` (``None``s left out) in order; ``None``
    when none is left."""
    present = [cb for cb in callbacks if cb is not None]
    if not present:
        return None
    if len(present) == 1:
        return present[0]

    def on_stage(name: str, event: str) -> None:
        for cb in present:
            cb(name, event)

    return on_stage


# --------------------------------------------------------------------------------------------------
# the client


class IGTLinkStreamer:
    """Streams the navigation to an OpenIGTLink server (3D Slicer) as it happens (module docstring).

    Messages are encoded with ``pyigtl`` and written to a plain TCP socket on the caller's thread
    with bounded waits (pyigtl's own client queues messages for a background thread, can wait
    without bound for the queue to empty and reconnects silently).

    Args:
        address: ``"HOST:PORT"`` of the server (e.g. ``"127.0.0.1:18944"``).
        timeout_s: the longest wait for the connection at the start, and for each message to be
            taken by the server.

    Raises:
        InputError: ``address`` is not ``HOST:PORT``.

    Use as a context manager (connects on entry, closes on exit), or call :meth:`start` and
    :meth:`close`; a message sent before :meth:`start` starts the link. Once constructed, every
    method is safe to call whatever the state of the link, and never raises.
    """

    def __init__(self, address: str, *, timeout_s: float = 2.0) -> None:
        self.host, self.port = parse_address(address)
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be positive, got {timeout_s}")
        self.timeout_s = float(timeout_s)
        self._sock: socket.socket | None = None
        self._started = False
        self._failed = False
        self._lock = threading.RLock()
        self._views: dict[str, tuple[Any, ...]] = {}
        self._names: dict[str, str] = {}

    # ----- state ----------------------------------------------------------------------------
    @property
    def address(self) -> str:
        """``HOST:PORT`` as given."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"

    @property
    def connected(self) -> bool:
        """Whether messages are being sent (false before the start, after a failure or close)."""
        return self._sock is not None

    def start(self) -> Self:
        """Connect to the server (once); on failure log one warning and stay a no-op."""
        with self._lock:
            if self._started:
                return self
            self._started = True
            try:
                sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
            except OSError as exc:
                self._give_up(f"no OpenIGTLink server answered at {self.address} ({_why(exc)})")
                return self
            self._sock = sock
            try:
                sock.settimeout(self.timeout_s)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError as exc:
                self._give_up(f"the connection to OpenIGTLink server {self.address} failed ({_why(exc)})")
                return self
            log.info("streaming the navigation to OpenIGTLink server %s", self.address)
            return self

    def close(self) -> None:
        """Close the connection (what was sent is delivered); later calls do nothing."""
        with self._lock:
            self._started = True
            sock, self._sock = self._sock, None
            if sock is None:
                return
            try:
                self._drain(sock)
                sock.shutdown(socket.SHUT_WR)
            except OSError:
                pass
            finally:
                sock.close()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # ----- the pipeline's callbacks ---------------------------------------------------------------
    def on_stage(self, name: str, event: str) -> None:
        """STRING ``Status``: ``"<name>: started"`` (event ``"start"``) or ``"<name>: done"``."""
        self._guarded(self._stage, name, event)

    def on_event(self, kind: str, data: Mapping[str, Any]) -> None:
        """Send what the event ``kind`` makes known (module docstring); unknown kinds are ignored."""
        self._guarded(self._event, kind, data)

    # ----- messages -----------------------------------------------------------------------------
    def send_status(self, text: str) -> None:
        """STRING ``Status`` with ``text`` (made ASCII)."""
        self._guarded(self._send_status, text)

    def send_transform(self, name: str, T_lps: np.ndarray) -> None:
        """TRANSFORM ``name`` with ``T_lps`` (4, 4, LPS both sides) converted to RAS."""
        self._guarded(self._send_transform, name, T_lps)

    def send_image(self, name: str, image: np.ndarray, camera: Camera) -> None:
        """IMAGE ``device_name(name)``: (rows, cols) ``image`` as float32 on the detector plane of
        ``camera`` (:func:`image_ijk_to_ras`)."""
        self._guarded(self._send_image, name, image, camera)

    # ----- internals ------------------------------------------------------------------------------
    def _guarded(self, fn: Callable[..., None], *args: Any) -> None:
        with self._lock:
            if not self._started:
                self.start()
            if self._sock is None:
                return
            try:
                fn(*args)
            except OSError as exc:
                self._give_up(f"the connection to OpenIGTLink server {self.address} was lost ({_why(exc)})")
            except Exception as exc:  # the link must never cost the navigation anything
                log.debug("OpenIGTLink message failed", exc_info=True)
                self._give_up(f"a message for OpenIGTLink server {self.address} failed ({_why(exc)})")

    def _give_up(self, what: str) -> None:
        if not self._failed:
            self._failed = True
            log.warning("%s; the navigation goes on without the live view", what)
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _stage(self, name: str, event: str) -> None:
        self._send_status(f"{name}: {'started' if event == 'start' else event}")

    def _event(self, kind: str, data: Mapping[str, Any]) -> None:
        if kind == "views":
            views = tuple(data["views"])
            self._views[str(data.get("prefix", ""))] = views
            for view in views:
                self._send_image(view.name, view.image, view.camera)
        elif kind == "registration":
            reg = data["registration"]
            views = getattr(reg, "views", None) or self._views.get(str(data.get("prefix", "")), ())
            for view, camera in zip(views, getattr(reg, "cameras_ct", ()), strict=False):
                self._send_image(view.name, view.image, camera)
            self._send_transform("CMToCT", reg.ct_from_cm)
            self._send_transform("FemurToCT", reg.ct_from_femur)
        elif kind == "plan":
            ct_from_femur = np.asarray(data["ct_from_femur"], dtype=np.float64)
            self._send_transform("PlanToCT", ct_from_femur @ np.asarray(data["femur_from_cm_target"]))
        elif kind == "status":
            status, reason = str(data.get("status", "")), str(data.get("reason", ""))
            self._send_status(f"navigation {status}" + (f": {reason}" if status != "ok" and reason else ""))

    def _image_device(self, view_name: str) -> str:
        """The device name of a view, the same for every message about it, distinct per view."""
        if view_name not in self._names:
            base, taken, k = device_name(view_name), set(self._names.values()), 2
            name = base
            while name in taken:
                suffix = f"_{k}"
                name, k = base[: DEVICE_NAME_MAX - len(suffix)] + suffix, k + 1
            self._names[view_name] = name
        return self._names[view_name]

    def _send_status(self, text: str) -> None:
        self._send(pyigtl.StringMessage(ascii_text(text), device_name="Status"))

    def _send_transform(self, name: str, T_lps: np.ndarray) -> None:
        self._send(pyigtl.TransformMessage(ras_from_lps_transform(T_lps), device_name=device_name(name)))

    def _send_image(self, name: str, image: np.ndarray, camera: Camera) -> None:
        pixels = np.nan_to_num(np.asarray(image, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        if pixels.ndim != 2:
            raise ValueError(f"view {name}: an image must be (rows, cols), got shape {pixels.shape}")
        msg = pyigtl.ImageMessage(
            np.ascontiguousarray(pixels[None]),  # (k, j, i) = (1, rows, cols): i = column u, j = row v
            ijk_to_world_matrix=image_ijk_to_ras(camera),
            world_coordinate_system="ras",
            device_name=self._image_device(name),
        )
        self._send(msg)

    def _send(self, message: Any) -> None:
        sock = self._sock
        if sock is None:
            return
        data = message.pack()
        self._drain(sock)
        sock.sendall(data)

    @staticmethod
    def _drain(sock: socket.socket) -> None:
        """Read (and drop) what the server sent; an orderly close by the server raises."""
        while select.select([sock], [], [], 0.0)[0]:
            if not sock.recv(65536):
                raise ConnectionResetError("the server closed the connection")


def _why(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or exc.__class__.__name__
