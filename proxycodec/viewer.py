"""``proxycodec view``: a local web viewer (viser) for a container, an anchor scene or a 3DGS PLY, SPZ or GLB.

Design: the server renders every frame with *our* renderer (``model.render``) and streams the image to the browser
as viser's background image, as nerfview does, instead of handing Gaussians to viser's client-side splat renderer.
Our colours and opacities depend on the view: the decoder's MLPs take the view direction (and distance) of every
anchor, the FiLM embedding takes the resolution ratio and the pixel-coverage gate dims Gaussians by their footprint at
the view's resolution; a 3DGS PLY's colours are spherical harmonics of the view direction. viser's client-side
renderer draws fixed splats and has none of this, so it would show another scene than the one we decode.

Frames: a camera message from the browser (position, orientation, vertical field of view, canvas size) becomes a
``Camera`` at the viewport's size (``camera_from_viser``), rendered at ``round(xi W) x round(xi H)`` pixels for the
resolution slider's ``xi`` (``camera.scaled(xi)``: the FiLM embedding and the gate see ``xi``), then upscaled
nearest-neighbour to the viewport, so the browser shows what that resolution looks like. One render thread does all
rendering (never two frames at once, never on the websocket thread); each client keeps only its latest request, so a
moving camera drops stale frames. Images go out as PNG (lossless; JPEG on request).

viser's camera convention (``ViewerCameraMessage``, ``CameraHandle``): ``wxyz`` and ``position`` are the rotation
and translation of ``T_world_camera`` (camera to world) with OpenCV camera axes (x right, y down, z forward): the
same axes as ``proxycodec.camera.Camera``, whose ``world_to_camera`` is its inverse. ``fov`` is the vertical field
of view in radians; ``image_width`` / ``image_height`` are the canvas's drawing-buffer size in pixels. The browser
stretches the background image over the whole viewport, so the principal point is the image centre and pixels are
square.

Sources open with ``scenes.load_any(torch_free=True)``: a container is decoded and rendered by the torch-free path
(``lite``: torch is never imported, ~1.5 s of the start). viser is imported only when a viewer starts
(``pip install -e '.[view]'``).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .camera import XI_MAX, Camera, check_xi
from .errors import ProxycodecError

VIEWER_NEEDS = "proxycodec view needs viser: pip install -e '.[view]'"

#: The resolution slider's range (the slider also reaches down to a smaller ``res`` given at start).
SLIDER_MIN, SLIDER_MAX, SLIDER_STEP = 0.1, XI_MAX, 0.01


class ViserMissing(ProxycodecError):
    """viser is not installed."""


def import_viser():
    try:
        import viser
    except ImportError:
        raise ViserMissing(VIEWER_NEEDS) from None
    return viser


# ==================================================================================================== camera conversion
def quat_to_matrix(wxyz) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> 3x3 rotation matrix (normalised first)."""
    q = np.asarray(wxyz, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if q.shape != (4,) or not math.isfinite(n) or n == 0.0:
        raise ProxycodecError(f"bad camera orientation {wxyz!r}")
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion (w, x, y, z) with w >= 0 (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def camera_from_viser(position, wxyz, fov: float, width: int, height: int, name: str = "viewer") -> Camera:
    """The ``Camera`` a viser client sees: ``position`` / ``wxyz`` of ``T_world_camera`` (OpenCV axes, as viser
    sends them), ``fov`` the vertical field of view (radians), ``width`` x ``height`` the image in pixels
    (principal point at its centre, square pixels)."""
    fov = float(fov)
    if not (math.isfinite(fov) and 0.0 < fov < math.pi):
        raise ProxycodecError(f"bad vertical field of view {fov!r}")
    R_wc = quat_to_matrix(wxyz)
    p = np.asarray(position, dtype=np.float64).reshape(3)
    w2c = np.eye(4)
    w2c[:3, :3] = R_wc.T
    w2c[:3, 3] = -R_wc.T @ p
    f = 0.5 * int(height) / math.tan(0.5 * fov)
    return Camera(w2c, f, f, int(width) / 2.0, int(height) / 2.0, int(width), int(height), name=name)


@dataclass(frozen=True)
class ViserPose:
    """What a viser camera is set to for a ``Camera`` (``viser_pose``)."""

    position: np.ndarray  # [3] camera centre
    wxyz: np.ndarray  # [4] rotation of T_world_camera
    fov: float  # vertical, radians
    look_at: np.ndarray  # [3] orbit centre on the optical axis
    up_direction: np.ndarray  # [3] the camera's -y axis in world


def viser_pose(camera: Camera, target=None) -> ViserPose:
    """The viser camera state showing ``camera``'s view: position, orientation, vertical field of view, an orbit
    centre on the optical axis (at the depth of ``target`` when given, else one unit ahead), the up direction (the
    camera's -y, so that viser's orbit controls keep its roll). The principal point is taken as centred."""
    R = camera.rotation  # world -> camera; rows are the camera axes in world
    c = camera.center
    forward = R[2]
    depth = 1.0
    if target is not None:
        depth = float(np.dot(np.asarray(target, dtype=np.float64) - c, forward))
        if not (math.isfinite(depth) and depth > 1e-6):
            depth = 1.0
    fov = 2.0 * math.atan(0.5 * camera.height / camera.fy)
    return ViserPose(c.copy(), matrix_to_quat(R.T), fov, c + depth * forward, -R[1].copy())


def set_client_camera(client, camera: Camera, target=None) -> None:
    """Move a viser client's camera to ``camera`` (its field of view, pose and roll)."""
    pose = viser_pose(camera, target)
    cam = client.camera
    with client.atomic():
        cam.fov = pose.fov
        cam.up_direction = pose.up_direction
        cam.position = pose.position
        cam.look_at = pose.look_at


# ==================================================================================================== frames
def upscale_nearest(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """``image`` [h, w, C] to [height, width, C]: each output pixel takes the input pixel under its centre."""
    h, w = image.shape[:2]
    if (w, h) == (width, height):
        return image
    rows = np.minimum(((np.arange(height) + 0.5) * (h / height)).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * (w / width)).astype(np.int64), w - 1)
    return image[rows[:, None], cols[None, :]]


@dataclass
class Frame:
    """One rendered view: ``image`` as rendered (float32 [h, w, 3]), ``display`` the uint8 image at the viewport size
    sent to the browser, ``stats`` the numbers of the GUI's text panel, ``text`` that panel (markdown)."""

    camera: Camera  # at the viewport's size (capped by max_size)
    xi: float
    image: np.ndarray
    display: np.ndarray
    stats: dict
    text: str
    client_id: int | None = None


def _fmt(n: int) -> str:
    return f"{int(n):,}"


def stats_text(stats: dict) -> str:
    head = (f"**{stats['xi'] * 100:.0f}%**: {stats['width']} x {stats['height']} px "
            f"(viewport {stats['viewport'][0]} x {stats['viewport'][1]})")
    lines = [head]
    if "anchors" in stats:
        lines += [f"Anchors in the scene: {_fmt(stats['anchors'])}",
                  f"Anchors the frustum keeps: {_fmt(stats['anchors_kept'])}",
                  f"Neural Gaussians decoded: {_fmt(stats['gaussians_decoded'])}",
                  f"Gaussians kept (gate, culls): {_fmt(stats['gaussians_projected'])}"]
    else:
        lines += [f"Gaussians in the scene: {_fmt(stats['gaussians'])}",
                  f"Gaussians projected: {_fmt(stats['gaussians_projected'])}"]
    lines.append(f"Render: {stats['render_ms']:.0f} ms")
    return "\n".join(f"- {s}" for s in lines)


def _view_camera(view, size, max_size: int | None) -> tuple[Camera, tuple[int, int]]:
    """(camera at the render's 100% size, viewport size) of a ``Camera`` or a viser camera state (anything with
    ``position``, ``wxyz``, ``fov``, ``image_width``, ``image_height``)."""
    if isinstance(view, Camera):
        W, H = (view.width, view.height) if size is None else (int(size[0]), int(size[1]))
        cam = view if (W, H) == (view.width, view.height) else view.sized(W, H)
    else:
        W, H = (int(view.image_width), int(view.image_height)) if size is None else (int(size[0]), int(size[1]))
        if W < 1 or H < 1:
            raise ProxycodecError(f"viewport {W} x {H} is empty")
        cam = None
    w, h = W, H
    if max_size is not None and max(W, H) > max_size:
        s = max_size / max(W, H)
        w, h = max(1, round(W * s)), max(1, round(H * s))
    if cam is None:
        cam = camera_from_viser(view.position, view.wxyz, view.fov, w, h)
    elif (w, h) != (W, H):
        cam = cam.sized(w, h)
    return cam, (W, H)


@dataclass(frozen=True)
class _ViewState:
    """A snapshot of a client's camera (viser replaces its state object on every message)."""

    position: np.ndarray
    wxyz: np.ndarray
    fov: float
    image_width: int
    image_height: int

    @staticmethod
    def of(handle) -> _ViewState:
        return _ViewState(np.array(handle.position, dtype=np.float64), np.array(handle.wxyz, dtype=np.float64),
                          float(handle.fov), int(handle.image_width), int(handle.image_height))

    def same(self, other: _ViewState | None) -> bool:
        return (other is not None and (self.image_width, self.image_height) == (other.image_width, other.image_height)
                and np.allclose(self.position, other.position, rtol=0, atol=1e-9)
                and np.allclose(self.wxyz, other.wxyz, rtol=0, atol=1e-9) and abs(self.fov - other.fov) < 1e-9)


# ==================================================================================================== the viewer
@dataclass(eq=False)
class Viewer:
    """A running viewer (``start_viewer``). ``url`` is where it serves; ``stop()`` ends it."""

    model: Any
    server: Any
    url: str
    initial_camera: Camera
    xi: float
    max_size: int | None = None
    log: Callable[[str], None] | None = print
    start_seconds: float = 0.0
    image_format: str = "png"
    frames_sent: int = 0
    last_frame: Frame | None = None
    _cond: threading.Condition = field(default_factory=threading.Condition, repr=False)
    _render_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)  # one render at a time
    _pending: dict = field(default_factory=dict, repr=False)  # client id -> (client, _ViewState)
    _last: dict = field(default_factory=dict, repr=False)  # client id -> (_ViewState, xi) last rendered
    _stopped: bool = False
    _thread: threading.Thread | None = field(default=None, repr=False)
    _gui: dict = field(default_factory=dict, repr=False)

    # ------------------------------------------------------------------ rendering (any thread; tests)
    def frame_for(self, view, size: tuple[int, int] | None = None, *, xi: float | None = None) -> Frame:
        """Render ``view`` (a ``Camera`` given at the viewport size, or a viser camera state) at ``xi`` (default:
        the slider's): ``model.render(camera, xi)`` at ``round(xi W) x round(xi H)`` pixels for the viewport
        ``size`` (width, height; default the camera's or the client's), upscaled nearest to the viewport."""
        xi = check_xi(self.xi if xi is None else xi)
        cam, (W, H) = _view_camera(view, size, self.max_size)
        with self._render_lock:
            t0 = time.perf_counter()
            r = self.model.render(cam, xi)
            ms = (time.perf_counter() - t0) * 1000.0
        image = _numpy(r.image)
        u8 = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)  # model.image_to_uint8's rounding
        h, w = image.shape[:2]
        stats: dict = {"xi": xi, "width": w, "height": h, "viewport": (W, H), "render_ms": ms,
                       "gaussians_projected": r.projected.count}
        vis = getattr(r, "visible_anchor_index", None)
        if vis is not None:
            stats.update(anchors=_num_anchors(self.model), anchors_kept=len(vis),
                         gaussians_decoded=int(r.gaussians.count))
        else:
            stats["gaussians"] = int(self.model.scene.num_gaussians)
        return Frame(cam, xi, image, upscale_nearest(u8, W, H), stats, stats_text(stats))

    def render_for(self, view, size: tuple[int, int] | None = None, *, xi: float | None = None) -> np.ndarray:
        """The image (float32 [h, w, 3]) the viewer renders for ``view`` (``frame_for``)."""
        return self.frame_for(view, size, xi=xi).image

    # ------------------------------------------------------------------ requests from clients
    def request(self, client) -> None:
        """Queue a frame for ``client``'s current camera (replacing any frame it still waits for)."""
        try:
            state = _ViewState.of(client.camera)
        except (AssertionError, AttributeError):  # no camera message from this client yet
            return
        with self._cond:
            self._pending[client.client_id] = (client, state)
            self._cond.notify_all()

    def request_all(self) -> None:
        for client in list(self.server.get_clients().values()):
            self.request(client)

    def set_xi(self, xi: float) -> None:
        self.xi = check_xi(xi)
        self.request_all()

    def wait_frames(self, n: int, timeout: float) -> bool:
        """Wait until ``frames_sent >= n`` (tests)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self.frames_sent < n:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def _loop(self) -> None:
        self._warm_up()
        while True:
            with self._cond:
                while not self._pending and not self._stopped:
                    self._cond.wait()
                if self._stopped:
                    return
                cid = next(iter(self._pending))
                client, state = self._pending.pop(cid)
                xi = self.xi
                last = self._last.get(cid)
            if last is not None and last[1] == xi and state.same(last[0]):
                continue  # the echo of a camera we already rendered
            try:
                frame = self.frame_for(state, xi=xi)
                frame.client_id = cid
                client.scene.set_background_image(frame.display, format=self.image_format, jpeg_quality=95)
                self._gui["stats"].content = frame.text
            except Exception as e:  # noqa: BLE001 (a failed frame must not end the viewer)
                if self.log:
                    self.log(f"view: frame failed: {type(e).__name__}: {e}")
                continue
            with self._cond:
                self._last[cid] = (state, xi)
                self.last_frame = frame
                self.frames_sent += 1
                self._cond.notify_all()

    def _warm_up(self) -> None:
        """Render a tiny frame first: loads the compositing kernels before the first client asks."""
        try:
            cam = self.initial_camera
            s = 48 / max(cam.width, cam.height)
            with self._render_lock:
                self.model.render(cam.sized(max(1, round(cam.width * s)), max(1, round(cam.height * s))), 1.0)
        except Exception:  # noqa: BLE001, S110 (only a warm-up: the first real frame reports its own error)
            pass

    # ------------------------------------------------------------------ clients
    def _on_connect(self, client) -> None:
        set_client_camera(client, self.initial_camera, _scene_center(self.model))
        client.camera.on_update(lambda handle: self.request(handle.client))
        self.request(client)

    def _on_disconnect(self, client) -> None:
        with self._cond:
            self._pending.pop(client.client_id, None)
            self._last.pop(client.client_id, None)

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
                self.server.stop()
        finally:
            if self._thread is not None and self._thread is not threading.current_thread():
                self._thread.join(timeout=30)


def _scene_center(model) -> np.ndarray:
    b = np.asarray(_bounds(model), dtype=np.float64)
    return b.mean(0)


def initial_camera_of(model) -> Camera:
    """The scene's first stored camera, else the first of ``default_cameras`` around its bounds."""
    from .camera import default_cameras

    cams = getattr(model, "cameras", None)
    return cams[0] if cams else default_cameras(None, _bounds(model))[0]


def _bounds(model) -> np.ndarray:
    """[2, 3] box of a ``SceneModel``'s anchors, an ``ExplicitModel``'s Gaussians or a ``lite.LiteScene``'s."""
    return model.bounds() if hasattr(model, "bounds") else model.scene.bounds()


def _num_anchors(model) -> int:
    return int(model.num_anchors) if hasattr(model, "num_anchors") else int(model.scene.num_anchors)


def _numpy(image) -> np.ndarray:
    """A render's image as float32 numpy (torch tensors detached; numpy from the torch-free path as is)."""
    return np.asarray(image.detach().cpu().numpy() if hasattr(image, "detach") else image, dtype=np.float32)


def start_viewer(source, *, host: str = "127.0.0.1", port: int = 8080, res: float = 1.0,
                 max_size: int | None = None, image_format: str = "png",
                 log: Callable[[str], None] | None = print) -> Viewer:
    """Load ``source`` (``scenes.load_any``: a container, an anchor PLY, an INRIA 3DGS PLY, a Scaffold-GS output) and
    serve a viewer of it on ``host:port`` (the next free port if taken); returns at once (``Viewer.stop()`` ends it).

    ``res``: the resolution slider's initial ratio; ``max_size``: cap on the longest side of the 100% render (the
    viewport's size otherwise); ``image_format``: how frames travel, ``png`` (lossless; ~0.4 s to encode 1920 x 1080
    on one core) or ``jpeg`` (quality 95, ~10 ms)."""
    t0 = time.perf_counter()
    res = check_xi(res)
    if image_format not in ("png", "jpeg"):
        raise ProxycodecError(f"image format must be png or jpeg, got {image_format!r}")
    if max_size is not None and int(max_size) < 1:
        raise ProxycodecError(f"max_size must be at least 1, got {max_size}")
    viser = import_viser()
    if isinstance(source, (str, os.PathLike)):
        from .scenes import load_any

        model = load_any(source, torch_free=True)
    else:
        model = source  # a model already in memory (tests)
    cam0 = initial_camera_of(model)
    with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: we print our own line
        server = viser.ViserServer(host=host, port=port, verbose=False)
    try:
        viewer = Viewer(model, server, f"http://{host}:{server.get_port()}", cam0, res,
                        None if max_size is None else int(max_size), log, image_format=image_format)
        server.gui.configure_theme(show_share_button=False, show_logo=False)
        pose = viser_pose(cam0, _scene_center(model))
        server.initial_camera.fov = pose.fov
        server.initial_camera.up = tuple(pose.up_direction)
        server.initial_camera.position = tuple(pose.position)
        server.initial_camera.look_at = tuple(pose.look_at)
        slider = server.gui.add_slider("Resolution", min=min(SLIDER_MIN, res), max=SLIDER_MAX, step=SLIDER_STEP,
                                       initial_value=res, hint="Render at this fraction of the viewport's pixels "
                                       "(shown upscaled, nearest)")
        viewer._gui["res"] = slider
        viewer._gui["stats"] = server.gui.add_markdown("waiting for a browser...")
        slider.on_update(lambda _: viewer.set_xi(float(slider.value)))
        server.on_client_connect(viewer._on_connect)
        server.on_client_disconnect(viewer._on_disconnect)
        viewer._thread = threading.Thread(target=viewer._loop, name="proxycodec-view-render", daemon=True)
        viewer._thread.start()
    except BaseException:
        with contextlib.redirect_stdout(io.StringIO()):
            server.stop()
        raise
    viewer.start_seconds = time.perf_counter() - t0
    if log:
        log(f"serving {viewer.url} in {viewer.start_seconds:.1f} s")
    return viewer
