"""``proxycodec view`` (``proxycodec.viewer``): rendering, the viser camera convention, the stats panel, the CLI, and
the page in a headless Chromium driven over its DevTools protocol (skipped without viser or Chromium)."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from proxycodec.bench.browser import ONLY_THE_CANVAS, DevTools, chromium, free_port, wait_for
from proxycodec.camera import Camera
from proxycodec.viewer import (
    VIEWER_NEEDS,
    camera_from_viser,
    matrix_to_quat,
    quat_to_matrix,
    upscale_nearest,
    viser_pose,
)

pytestmark = pytest.mark.usefixtures("one_thread")

CENTER = (0.0, 0.0, 0.3)  # the built-in scene's middle


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 100.0 if mse == 0 else min(100.0, 10 * math.log10(255.0**2 / mse))


@pytest.fixture(scope="module")
def tiny():
    """Every 8th anchor of the built-in scene (~820 anchors): renders in tens of milliseconds."""
    import torch

    from proxycodec.model import SceneModel
    from proxycodec.sample import sample_model

    m = sample_model()
    s = m.scene
    return SceneModel(s.subset(torch.arange(0, s.num_anchors, 8)), m.decoder, m.cameras, m.background)


@pytest.fixture(scope="module")
def viewer(tiny):
    pytest.importorskip("viser", reason="the viewer needs viser (pip install -e '.[view]')")
    from proxycodec.viewer import start_viewer

    v = start_viewer(tiny, port=free_port(), res=0.5, log=None)
    yield v
    v.stop()


# ============================================================================================== camera convention
def _cameras():
    yield Camera.look_at((2.0, -1.5, 1.2), CENTER, fov_x_deg=55, width=160, height=90)
    yield Camera.look_at((-0.3, 2.4, 0.5), (0.2, 0.0, 0.2), fov_x_deg=30, width=64, height=128)
    yield Camera.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_x_deg=80, width=100, height=100)
    tilted = Camera.look_at((1.0, 1.0, 1.0), (0.0, 0.0, 0.0), up=(0.3, -0.2, 1.0), fov_x_deg=40, width=120, height=80)
    yield tilted


@pytest.mark.parametrize("cam", list(_cameras()))
def test_viser_pose_round_trips(cam):
    """Camera -> the viser state showing it -> Camera: the same pose, field of view and intrinsics."""
    pose = viser_pose(cam, CENTER)
    back = camera_from_viser(pose.position, pose.wxyz, pose.fov, cam.width, cam.height)
    np.testing.assert_allclose(back.world_to_camera, cam.world_to_camera, atol=1e-12)
    assert back.fx == pytest.approx(cam.fx, rel=1e-12) and back.fy == pytest.approx(cam.fy, rel=1e-12)
    assert (back.cx, back.cy, back.width, back.height) == (cam.cx, cam.cy, cam.width, cam.height)
    # the orbit centre lies on the optical axis, the up direction is the camera's -y
    z = cam.rotation[2]
    assert np.cross(pose.look_at - pose.position, z) == pytest.approx(np.zeros(3), abs=1e-12)
    assert float(np.dot(pose.look_at - pose.position, z)) > 0
    np.testing.assert_allclose(pose.up_direction, -cam.rotation[1], atol=1e-12)


def test_viser_camera_convention():
    """viser's (position, wxyz) is T_world_camera with OpenCV axes, fov vertical: with the identity rotation the camera
    looks along world +z, image x along world x, image y along world y; a point at the vertical half-angle falls on
    the bottom edge."""
    fov = math.radians(50)
    cam = camera_from_viser((1.0, 2.0, 3.0), (1.0, 0.0, 0.0, 0.0), fov, 200, 100)

    def pixel(p):
        q = cam.world_to_camera @ np.r_[p, 1.0]
        return cam.K @ q[:3] / q[2]

    assert pixel((1.0, 2.0, 4.0))[:2] == pytest.approx((100.0, 50.0))
    assert pixel((1.0, 2.0 + math.tan(fov / 2), 4.0))[:2] == pytest.approx((100.0, 100.0))
    assert pixel((1.0 + 2 * math.tan(fov / 2), 2.0, 4.0))[:2] == pytest.approx((200.0, 50.0))  # square pixels
    # a camera rotated 90 degrees about world z: its x axis is world +y
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    cam = camera_from_viser((0.0, 0.0, 0.0), (c, 0.0, 0.0, s), fov, 100, 100)
    np.testing.assert_allclose(cam.rotation, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_quaternions_match_viser():
    viser = pytest.importorskip("viser")
    rng = np.random.default_rng(0)
    for _ in range(20):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        R = quat_to_matrix(q)
        np.testing.assert_allclose(R, viser.transforms.SO3(q).as_matrix(), atol=1e-12)
        back = matrix_to_quat(R)
        assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-12


def test_upscale_nearest():
    img = np.arange(2 * 3 * 1).reshape(2, 3, 1)
    up = upscale_nearest(img, 6, 4)
    assert up.shape == (4, 6, 1)
    np.testing.assert_array_equal(up[..., 0], [[0, 0, 1, 1, 2, 2]] * 2 + [[3, 3, 4, 4, 5, 5]] * 2)
    assert upscale_nearest(img, 3, 2) is img


# ============================================================================================== frames and stats
def test_render_for_is_the_model_render(viewer, tiny):
    """The viewer renders a camera given at the viewport size at round(xi W) x round(xi H): model.render exactly;
    the browser gets it upscaled nearest to the viewport."""
    from proxycodec.model import image_to_uint8

    cam = Camera.look_at((2.0, -1.5, 1.2), CENTER, fov_x_deg=55, width=90, height=60)
    for xi in (1.0, 0.5, 0.3):
        ref = tiny.render(cam, xi)
        np.testing.assert_array_equal(viewer.render_for(cam, xi=xi), ref.image.numpy())
        w, h = max(1, round(xi * 90)), max(1, round(xi * 60))
        np.testing.assert_array_equal(viewer.render_for(cam, xi=xi), tiny.render(cam, xi, size=(w, h)).image.numpy())
        f = viewer.frame_for(cam, xi=xi)
        assert f.image.shape == (h, w, 3) and f.display.shape == (60, 90, 3) and f.display.dtype == np.uint8
        np.testing.assert_array_equal(f.display, upscale_nearest(image_to_uint8(ref.image), 90, 60))
    # a viser camera state (what a browser sends): the same as the Camera it describes
    pose = viser_pose(cam, CENTER)
    state = SimpleNamespace(position=pose.position, wxyz=pose.wxyz, fov=pose.fov, image_width=90, image_height=60)
    np.testing.assert_allclose(viewer.render_for(state, xi=0.5), tiny.render(cam, 0.5).image.numpy(), atol=1e-5)
    assert viewer.render_for(cam).shape == (30, 45, 3)  # the slider's xi (0.5) by default


def test_stats_follow_the_view(viewer, tiny):
    n = tiny.scene.num_anchors
    whole = viewer.frame_for(Camera.look_at((2.6, -2.0, 1.8), CENTER, fov_x_deg=60, width=64, height=48), xi=1.0)
    part = viewer.frame_for(Camera.look_at((0.0, 0.0, 0.3), (3.0, 0.0, 0.3), fov_x_deg=60, width=64, height=48),
                            xi=1.0)
    s, p = whole.stats, part.stats
    assert s["anchors"] == p["anchors"] == n
    assert s["anchors_kept"] == n and 0 < p["anchors_kept"] < n // 2  # looking out from the middle
    assert 0 < s["gaussians_projected"] <= s["gaussians_decoded"] <= 10 * s["anchors_kept"]
    assert p["gaussians_decoded"] < s["gaussians_decoded"]
    for f in (whole, part):
        st = f.stats
        for key in ("anchors", "anchors_kept", "gaussians_decoded", "gaussians_projected"):
            assert f"{st[key]:,}" in f.text
        assert f"{st['render_ms']:.0f} ms" in f.text and "64 x 48 px" in f.text
    assert "Anchors the frustum keeps: " + f"{p['anchors_kept']:,}" in part.text


def test_stats_of_a_3dgs_ply():
    from proxycodec.formats.inria_ply import GaussianPly

    from proxycodec.explicit import ExplicitModel
    from proxycodec.viewer import Frame, Viewer

    rng = np.random.default_rng(1)
    n = 300
    g = GaussianPly(rng.uniform(-0.5, 0.5, (n, 3)), rng.normal(size=(n, 4, 3)) * 0.3, np.full(n, 1.0),
                    np.full((n, 3), math.log(0.03)), rng.normal(size=(n, 4)))
    model = ExplicitModel(g)
    v = Viewer(model, None, "", Camera.look_at((2, 0, 0), (0, 0, 0), width=48, height=32), 1.0)
    cam = Camera.look_at((2.0, 0.3, 0.4), (0, 0, 0), fov_x_deg=50, width=48, height=32)
    f = v.frame_for(cam)
    assert isinstance(f, Frame)
    np.testing.assert_array_equal(f.image, model.render(cam, 1.0).image.numpy())
    assert f.stats["gaussians"] == n and 0 < f.stats["gaussians_projected"] <= n and "anchors" not in f.stats
    assert f"Gaussians in the scene: {n}" in f.text
    assert f"Gaussians projected: {f.stats['gaussians_projected']}" in f.text


def test_latest_camera_wins(viewer, tiny):
    """Requests queued while the render thread is busy collapse into the newest one; its frame goes to the client
    as a PNG at the viewport size and its numbers to the text panel."""
    sent = []
    cams = [Camera.look_at((2.0 + 0.1 * i, -1.5, 1.2), CENTER, fov_x_deg=55, width=40, height=30) for i in range(5)]
    scene = SimpleNamespace(set_background_image=lambda img, format, **kw: sent.append((img, format)))
    client = SimpleNamespace(client_id=-7, camera=None, scene=scene)
    n0 = viewer.frames_sent
    with viewer._cond:  # the render thread cannot take a request meanwhile
        for c in cams:
            p = viser_pose(c, CENTER)
            client.camera = SimpleNamespace(position=p.position, wxyz=p.wxyz, fov=p.fov, image_width=40,
                                            image_height=30)
            viewer.request(client)
    assert viewer.wait_frames(n0 + 1, 60)
    time.sleep(0.2)
    assert viewer.frames_sent == n0 + 1 and len(sent) == 1
    img, fmt = sent[0]
    assert fmt == "png" and img.shape == (30, 40, 3)
    f = viewer.last_frame
    assert f.client_id == -7 and f.xi == viewer.xi
    np.testing.assert_allclose(f.camera.world_to_camera, cams[-1].world_to_camera, atol=1e-9)
    np.testing.assert_array_equal(img, f.display)
    assert viewer._gui["stats"].content == f.text
    # the same camera again (a browser echoes what it was sent) is not rendered twice
    viewer.request(client)
    time.sleep(0.5)
    assert viewer.frames_sent == n0 + 1
    viewer._on_disconnect(client)


def test_start_from_a_file_serves_and_reports_its_time(tiny, tmp_path):
    pytest.importorskip("viser")
    from proxycodec.viewer import start_viewer

    ply, _ = tiny.save(tmp_path / "tiny.ply")
    lines = []
    v = start_viewer(ply, port=free_port(), log=lines.append)
    try:
        assert len(lines) == 1 and re.fullmatch(rf"serving {re.escape(v.url)} in \d+\.\d s", lines[0]), lines
        assert v.start_seconds < 30
        assert v.model.scene.num_anchors == tiny.scene.num_anchors
        np.testing.assert_allclose(v.initial_camera.world_to_camera, tiny.cameras[0].world_to_camera)
        with urllib.request.urlopen(v.url, timeout=10) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
    finally:
        v.stop()


def test_a_container_is_viewed_by_the_torch_free_path(tiny, tmp_path):
    """A container loads with ``lite`` (no torch import: the viewer starts ~1.5 s sooner); its frames are the
    torch-free render's, bit for bit, and within the torch-free path's float32 distance of the torch render."""
    pytest.importorskip("viser")
    from proxycodec import codec, lite
    from proxycodec.viewer import start_viewer

    pxc = tmp_path / "t.pxc"
    codec.encode(tiny, pxc, distill=False, predictor_iters=20, zstd_level=3)
    v = start_viewer(pxc, port=free_port(), log=None)
    try:
        assert isinstance(v.model, lite.LiteScene)
        cam = tiny.cameras[0].sized(96, 72)
        f = v.frame_for(cam, xi=0.5)
        np.testing.assert_array_equal(f.image, lite.decode(pxc).render(cam, 0.5).image)
        from test_decode_lite import assert_renders_agree  # float32 paths: decisions may flip on another CPU

        assert_renders_agree(codec.decode(pxc), lite.decode(pxc), cam, 0.5)
        assert f.stats["anchors"] == tiny.scene.num_anchors and f.stats["gaussians_decoded"] > 0
    finally:
        v.stop()
    code = ("import sys; from proxycodec.viewer import start_viewer; "
            f"v = start_viewer({str(pxc)!r}, port={free_port()}, log=None); v.stop(); "
            "print('torch' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip().splitlines()[-1] == "False", r.stdout + r.stderr


# ============================================================================================== command line
def test_cli_without_viser_is_one_line(monkeypatch, tmp_path):
    from proxycodec.cli.main import cli

    monkeypatch.setitem(sys.modules, "viser", None)  # import viser -> ImportError
    r = CliRunner().invoke(cli, ["view", str(tmp_path / "scene.pxc")])
    assert r.exit_code == 2, r.output
    lines = r.output.strip().splitlines()
    assert len(lines) == 1 and VIEWER_NEEDS in lines[0] and "Traceback" not in r.output


def test_cli_help_and_no_viser_import_for_other_commands():
    from proxycodec.cli.main import cli

    r = CliRunner().invoke(cli, ["view", "--help"])
    assert r.exit_code == 0 and "--port" in r.output and "--res" in r.output
    code = "import sys, proxycodec.cli.main; assert 'viser' not in sys.modules, 'viser imported'"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_cli_serves_until_ctrl_c(tiny, tmp_path):
    pytest.importorskip("viser")
    import signal

    ply, _ = tiny.save(tmp_path / "tiny.ply")
    port = free_port()
    # SIGINT back to its default in the child: a test run started as a background job (``cmd &`` in a script, as
    # `.ci/run` may be) inherits SIGINT ignored, and a Python started so never raises KeyboardInterrupt
    p = subprocess.Popen([sys.executable, "-m", "proxycodec.cli", "view", str(ply), "--port", str(port), "--res", "0.5"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        line = p.stdout.readline()
        assert re.fullmatch(rf"serving http://127\.0\.0\.1:{port} in \d+\.\d s\n", line), line
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=10) as r:
            assert r.status == 200
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=60)
        assert p.returncode == 0 and "Traceback" not in out and "stopping" in out, out
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate(timeout=30)


# ============================================================================================== in a browser
def _close(a: Camera, b: Camera, tol: float = 1e-6) -> bool:
    return (np.abs(a.world_to_camera - b.world_to_camera).max() < tol and abs(a.fy / b.fy - 1) < tol
            and (a.width, a.height) == (b.width, b.height))


def _settled(viewer, seen: list) -> Camera:
    """The browser's camera once it has sent no camera message for 1 s (the orbit controls ease out), after the
    viewer has sent its frame."""
    count = [len(seen), time.monotonic()]

    def settled():
        if len(seen) != count[0]:
            count[:] = [len(seen), time.monotonic()]
        return time.monotonic() - count[1] > 1.0

    wait_for(settled, 20, "the camera to settle")
    return wait_for(lambda: seen[-1] if viewer.last_frame is not None and _close(viewer.last_frame.camera, seen[-1])
                    else None, 20, "the frame of the browser's last camera")


def _shows(browser, viewer, ref: np.ndarray, camera: Camera, seen: list, bad_png, timeout: float = 30.0):
    """Wait until two screenshots in a row are within 30 dB of ``ref`` (the page settled on our render of
    ``camera``); on a timeout, fail with what the page showed instead (and keep that screenshot in ``bad_png``)."""
    deadline, before, raw, img = time.monotonic() + timeout, False, b"", None
    while time.monotonic() < deadline:
        raw, img = browser.screenshot()
        ok = img.shape == ref.shape and _psnr(img, ref) > 30
        if ok and before:
            return raw, img
        before = ok
        time.sleep(0.2)
    bad_png.write_bytes(raw)
    f = viewer.last_frame
    why = [f"screenshot {img.shape} against our render {ref.shape}"]
    if img.shape == ref.shape:
        why.append(f"PSNR {_psnr(img, ref):.2f} dB")
    if f is not None and f.display.shape == img.shape:
        why.append(f"{_psnr(img, f.display):.2f} dB against the viewer's last frame")
    if f is not None:
        off = np.abs(f.camera.world_to_camera - camera.world_to_camera).max()
        why.append(f"last frame {off:.2e} off the camera, {f.stats['width']} x {f.stats['height']} px at xi {f.xi}")
    if seen:
        off = np.abs(seen[-1].world_to_camera - camera.world_to_camera).max()
        why.append(f"{len(seen)} camera messages, the last {off:.2e} off, {seen[-1].width} x {seen[-1].height} px")
    raise AssertionError(f"the page did not settle on our render ({bad_png}): " + "; ".join(why))


def test_browser_shows_our_render(viewer, tiny, tmp_path):
    """Load the page in headless Chromium, move the camera from the server, then by dragging in the page: the browser
    reports back the pose it was given (the convention, through three.js), a viser object placed at a known point
    appears where our camera projects it, and the screenshot of the viewport is our own render of that camera."""
    from proxycodec.model import image_to_uint8
    from proxycodec.viewer import set_client_camera

    exe = chromium()
    if exe is None:
        pytest.skip("no Chromium (Debian: apt-get install chromium)")
    W, H = 640, 400
    browser = DevTools(exe, tmp_path / "profile", W, H)
    try:
        n0 = viewer.frames_sent
        # fixedDpr: viser lowers the canvas resolution when the page draws slowly (software WebGL here); the
        # viewer follows the canvas size it is sent, and the browser would stretch that canvas bilinearly
        browser.call("Page.navigate", url=viewer.url + "/?fixedDpr=1")
        assert viewer.wait_frames(n0 + 1, 90), "the viewer sent no frame to the browser"
        client = wait_for(lambda: next(iter(viewer.server.get_clients().values()), None), 10, "the client")
        seen = []  # cameras the browser reports
        client.camera.on_update(lambda h: seen.append(camera_from_viser(h.position, h.wxyz, h.fov, h.image_width,
                                                                         h.image_height)))
        # the initial camera is the scene's first, at the viewport's size with its vertical field of view (the
        # page may first report viser's default camera, before it gets ours)
        cam0 = tiny.cameras[0]
        first = wait_for(lambda: viewer.last_frame.camera if np.abs(viewer.last_frame.camera.world_to_camera
                                                                 - cam0.world_to_camera).max() < 1e-6 else None,
                      20, "a frame of the scene's first camera")
        assert (first.width, first.height) == (W, H)
        assert math.atan(0.5 * H / first.fy) == pytest.approx(math.atan(0.5 * cam0.height / cam0.fy), rel=1e-6)

        # 1. from the server
        target = Camera.look_at((1.7, -1.9, 1.25), (0.1, 0.05, 0.3), fov_x_deg=62, width=W, height=H)
        set_client_camera(client, target, CENTER)
        wait_for(lambda: any(_close(c, target) for c in seen), 20, "the browser to report the new camera")
        shown = _settled(viewer, seen)
        assert _close(shown, target), ("the browser moved on from the camera it was given: "
                                       f"{np.abs(shown.world_to_camera - target.world_to_camera).max():.2e} off, "
                                       f"fy {shown.fy / target.fy - 1:+.2e}, {shown.width} x {shown.height} px")
        ref = upscale_nearest(image_to_uint8(tiny.render(target, viewer.xi).image), W, H)
        browser.evaluate(ONLY_THE_CANVAS)

        raw, img = _shows(browser, viewer, ref, target, seen, tmp_path / "first_mismatch.png")
        psnr = _psnr(img, ref)
        shot = tmp_path / "view_screenshot.png"
        shot.write_bytes(raw)
        shutil.copyfile(shot, "/tmp/view_screenshot.png")
        print(f"screenshot {shot} (and /tmp/view_screenshot.png): PSNR {psnr:.2f} dB against our render "
              f"(max |diff| {int(np.abs(img.astype(int) - ref.astype(int)).max())})")
        browser.evaluate("document.getElementById('only-the-canvas').remove()")  # the page as a user sees it
        time.sleep(0.5)
        raw_gui, _ = browser.screenshot()
        (tmp_path / "view_screenshot_gui.png").write_bytes(raw_gui)
        shutil.copyfile(tmp_path / "view_screenshot_gui.png", "/tmp/view_screenshot_gui.png")
        browser.evaluate(ONLY_THE_CANVAS)

        # 2. a viser object where our camera projects a point: the same pixel in the browser's own 3D rendering
        ref = ref.astype(int)
        for u, v in ((0.2 * W, 0.25 * H), (0.85 * W, 0.8 * H)):
            p_cam = 1.5 * np.linalg.solve(target.K, [u, v, 1.0])
            p = target.rotation.T @ (p_cam - target.translation)
            marker = viewer.server.scene.add_icosphere("/marker", radius=0.02, color=(0, 255, 0), position=tuple(p))

            def drawn():  # the pixels the marker changed in our image
                _, img = browser.screenshot()
                ys, xs = np.nonzero(np.abs(img.astype(int) - ref).sum(-1) > 60)
                return (xs.mean() + 0.5, ys.mean() + 0.5) if len(xs) >= 4 else None

            got = wait_for(drawn, 20, "the marker", step=0.2)
            marker.remove()
            wait_for(lambda: drawn() is None, 20, "the marker to go", step=0.2)
            print(f"marker at ({u:.1f}, {v:.1f}) px by our camera, ({got[0]:.2f}, {got[1]:.2f}) px in the browser")
            assert got == pytest.approx((u, v), abs=1.0), (got, (u, v))

        # 3. by dragging in the page: the last frame is our render of the camera the browser reports
        n1 = viewer.frames_sent
        browser.drag(0.5 * W, 0.5 * H, 0.65 * W, 0.45 * H)
        wait_for(lambda: viewer.frames_sent > n1, 20, "a frame after the drag")
        last = _settled(viewer, seen)
        assert not _close(last, target), "the drag did not move the camera"
        ref = upscale_nearest(image_to_uint8(tiny.render(last, viewer.xi).image), W, H)
        _, img = _shows(browser, viewer, ref, last, seen, tmp_path / "drag_mismatch.png")
        print(f"after the drag: PSNR {_psnr(img, ref):.2f} dB")
    finally:
        browser.close()
