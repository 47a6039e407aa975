"""Undistortion of COLMAP radial cameras (formats/undistort.py) and its use by load_colmap / the CLI.

Synthetic and fast; the real-data test on ../shared/data/colmap_phone/beer skips with a clear reason when the data
is absent.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import shared_data_path
from PIL import Image
from proxycodec.formats.colmap import load_colmap, read_colmap_model
from proxycodec.formats.undistort import (
    DistortedCamera,
    RemapCache,
    Undistorter,
    distort,
    distortion,
    undistort,
)

from proxycodec.errors import ProxycodecError

# (model, params) with strong but invertible distortion, for a 160x120 image
CAMERAS = [
    ("SIMPLE_RADIAL", [150.0, 81.0, 59.5, 0.08]),
    ("RADIAL", [150.0, 79.0, 61.0, -0.09, 0.02]),
    ("OPENCV", [150.0, 155.0, 80.5, 60.0, 0.05, -0.01, 0.002, -0.003]),
    ("FULL_OPENCV", [150.0, 148.0, 80.0, 60.0, -0.06, 0.01, -0.001, 0.002, 0.003, 0.02, -0.01, 0.004]),
]
W, H = 160, 120


def _grid(w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    return np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)


# ============================================================================================ (a) formulas
class TestDistortionFormulas:
    """COLMAP's Distortion() for each model, against values computed by hand at (u, v) = (0.3, -0.2)."""

    u, v = 0.3, -0.2  # r2 = 0.13, r4 = 0.0169, r6 = 0.002197, u*v = -0.06

    def test_simple_radial(self):
        du, dv = distortion("SIMPLE_RADIAL", [0.1], self.u, self.v)  # radial = 0.1 * 0.13 = 0.013
        assert (float(du), float(dv)) == pytest.approx((0.0039, -0.0026), abs=1e-15)
        assert tuple(map(float, distort("SIMPLE_RADIAL", [0.1], self.u, self.v))) == pytest.approx(
            (0.3039, -0.2026), abs=1e-15
        )

    def test_radial(self):
        du, dv = distortion("RADIAL", [0.1, -0.05], self.u, self.v)  # radial = 0.013 - 0.05 * 0.0169 = 0.012155
        assert (float(du), float(dv)) == pytest.approx((0.0036465, -0.002431), abs=1e-15)

    def test_opencv(self):
        # du = 0.3 * 0.012155 + 2 * 0.01 * (-0.06) + (-0.02) * (0.13 + 2 * 0.09) = 0.0036465 - 0.0012 - 0.0062
        # dv = -0.2 * 0.012155 + 2 * (-0.02) * (-0.06) + 0.01 * (0.13 + 2 * 0.04) = -0.002431 + 0.0024 + 0.0021
        du, dv = distortion("OPENCV", [0.1, -0.05, 0.01, -0.02], self.u, self.v)
        assert (float(du), float(dv)) == pytest.approx((-0.0037535, 0.002069), abs=1e-15)

    def test_full_opencv(self):
        # radial = (1 + 0.1 * 0.13 - 0.05 * 0.0169 + 0.02 * 0.002197) / (1 + 0.05 * 0.13 + 0.01 * 0.0169 - 0.01 * 0.002197)
        #        = 1.01219894 / 1.00664703
        radial = 1.01219894 / 1.00664703
        du, dv = distortion("FULL_OPENCV", [0.1, -0.05, 0.01, -0.02, 0.02, 0.05, 0.01, -0.01], self.u, self.v)
        assert float(du) == pytest.approx(0.3 * radial - 0.0012 - 0.0062 - 0.3, abs=1e-15)
        assert float(dv) == pytest.approx(-0.2 * radial + 0.0024 + 0.0021 + 0.2, abs=1e-15)

    def test_full_opencv_reduces_to_opencv(self):
        rng = np.random.default_rng(0)
        u, v = rng.uniform(-0.6, 0.6, (2, 100))
        a = distortion("OPENCV", [0.1, -0.05, 0.01, -0.02], u, v)
        b = distortion("FULL_OPENCV", [0.1, -0.05, 0.01, -0.02, 0, 0, 0, 0], u, v)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-15)

    def test_bad_coefficients(self):
        with pytest.raises(ProxycodecError, match="needs 2 finite"):
            distortion("RADIAL", [0.1], 0.0, 0.0)
        with pytest.raises(ProxycodecError, match="cannot undistort the OPENCV_FISHEYE model"):
            distortion("OPENCV_FISHEYE", [0, 0, 0, 0], 0.0, 0.0)


# ============================================================================================ (b) round trip
@pytest.mark.parametrize("model,params", CAMERAS)
def test_round_trip(model, params):
    cam = DistortedCamera.from_colmap(model, params, W, H)
    e = cam.extra
    # points of the undistorted (output) image, the whole frame
    x, y = _grid(W, H)
    fx, fy, cx, cy = cam.pinhole()
    u, v = (x - cx) / fx, (y - cy) / fy
    ud, vd = distort(model, e, u, v)
    u2, v2 = undistort(model, e, ud, vd)
    assert max(np.abs(u2 - u).max(), np.abs(v2 - v).max()) < 1e-9
    # points of the distorted (source) image, the whole frame
    ud, vd = (x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy
    u, v = undistort(model, e, ud, vd)
    ud2, vd2 = distort(model, e, u, v)
    assert max(np.abs(ud2 - ud).max(), np.abs(vd2 - vd).max()) < 1e-9


# ============================================================================================ (c) images
def _pattern(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A smooth colour checker on the normalised plane (period 0.2: ~30 px at f = 150)."""
    a = np.sin(2 * math.pi * u / 0.2)
    b = np.sin(2 * math.pi * v / 0.2)
    return np.stack([0.5 + 0.4 * a * b, 0.5 + 0.4 * a, 0.5 + 0.4 * b], axis=-1).astype(np.float32)


def _distorted_photo(cam: DistortedCamera) -> np.ndarray:
    """What the distorted camera sees of :func:`_pattern`: each source pixel centre undistorted, then evaluated."""
    x, y = _grid(cam.width, cam.height)
    u, v = undistort(cam.model, cam.extra, (x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy)
    return _pattern(u, v)


@pytest.mark.parametrize("model,params", CAMERAS)
def test_undistorted_image_matches_the_pinhole_camera(model, params):
    cam = DistortedCamera.from_colmap(model, params, W, H)
    photo = _distorted_photo(cam)
    out = Undistorter(cam)(photo)
    assert out.shape == photo.shape and out.dtype == np.float32
    fx, fy, cx, cy = cam.pinhole()
    x, y = _grid(W, H)
    truth = _pattern((x - cx) / fx, (y - cy) / fy)
    err = np.abs(out - truth)
    # bilinear interpolation error of the pattern (its product term has a ~21 px diagonal period): <= 4.8e-3 seen
    assert err.max() < 8e-3 and err.mean() < 1.5e-3
    # the test can fail: the photo as it is (no undistortion), or undistorted but paired with the distorted
    # camera's focal (no rescaling), is far off
    assert np.abs(photo - truth).max() > 0.05
    assert np.abs(out - _pattern((x - cx) / cam.fx, (y - cy) / cam.fy)).max() > 0.05


def test_remap_is_deterministic_and_cached():
    cam = DistortedCamera.from_colmap(*CAMERAS[2], W, H)
    photo = _distorted_photo(cam)
    cache = RemapCache()
    a = Undistorter(cam, cache)(photo)
    assert cache.nbytes == W * H * 12
    twin = DistortedCamera.from_colmap(*CAMERAS[2], W, H)  # an equal camera shares the table
    b = Undistorter(twin, cache)(photo)
    assert cache.nbytes == W * H * 12
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, Undistorter(cam)(photo.copy()))
    small = RemapCache(max_bytes=1000)  # too small to hold a table: computed each time, same result
    np.testing.assert_array_equal(a, Undistorter(cam, small)(photo))
    assert small.nbytes == 0


# ============================================================================================ (d) no blank pixels
@pytest.mark.parametrize("k1", np.linspace(-0.1, 0.1, 9).tolist())
def test_every_output_pixel_is_valid(k1):
    w, h = 72, 128  # the beer scene's portrait shape, at a tenth
    cam = DistortedCamera.from_colmap("SIMPLE_RADIAL", [112.0, 36.0, 64.0, k1], w, h)
    x, y = cam.source_map()
    assert x.min() >= 0.5 and x.max() <= w - 0.5 and y.min() >= 0.5 and y.max() <= h - 0.5
    # ...and the scale is the tightest: the output touches the source border (to 1e-6 px)
    margin = min(x.min() - 0.5, w - 0.5 - x.max(), y.min() - 0.5, h - 0.5 - y.max())
    assert margin < 1e-6
    if k1 > 0:  # pincushion: zoom in; barrel: zoom out
        assert cam.scale > 1
    elif k1 < 0:
        assert cam.scale < 1
    ones = np.ones((h, w, 3), np.float32)
    np.testing.assert_array_equal(Undistorter(cam)(ones), ones)


def test_impossible_distortion_is_refused():
    cam = DistortedCamera.from_colmap("SIMPLE_RADIAL", [10.0, 2.0, 2.0, 0.1], 4, 4)
    assert cam.scale > 0  # fine
    with pytest.raises(ProxycodecError, match="cannot undistort"):
        DistortedCamera.from_colmap("SIMPLE_RADIAL", [10.0, 80.0, 2.0, 0.1], 4, 4).pinhole()  # centre outside
    with pytest.raises(ProxycodecError, match="at least 2x2"):
        DistortedCamera.from_colmap("SIMPLE_RADIAL", [10.0, 0.5, 2.0, 0.1], 1, 4)


# ============================================================================================ datasets
def _qvec_look_at(eye) -> tuple[np.ndarray, np.ndarray]:
    from proxycodec.camera import Camera

    cam = Camera.look_at(eye, (0, 0, 0), (0, 0, 1), width=W, height=H)
    R = cam.rotation
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return np.array([w, x, y, z]), cam.translation


def _scene(root: Path, cameras: list[tuple[str, list[float]]], *, scale: int = 1, folder: str = "images") -> None:
    """A COLMAP text model with one image per camera, images rendered by the distorted cameras."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    cam_lines, img_lines = [], []
    for i, (model, params) in enumerate(cameras):
        cam_lines.append(f"{i + 1} {model} {W} {H} " + " ".join(repr(float(p)) for p in params))
        q, t = _qvec_look_at((4 * math.cos(i), 4 * math.sin(i), 1.0))
        img_lines += [f"{i + 1} " + " ".join(repr(float(x)) for x in (*q, *t)) + f" {i + 1} im{i}.png", ""]
        try:
            photo = _distorted_photo(DistortedCamera.from_colmap(model, params, W, H))
        except ProxycodecError:  # a model we cannot render: any image will do
            photo = np.full((H, W, 3), 0.5, np.float32)
        im = Image.fromarray(np.round(photo * 255).astype(np.uint8))
        if scale != 1:
            im = im.resize((W // scale, H // scale), Image.Resampling.BOX)
        (root / folder).mkdir(exist_ok=True)
        im.save(root / folder / f"im{i}.png")
    (sparse / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (sparse / "images.txt").write_text("\n".join(img_lines) + "\n")


class TestLoadColmapUndistorted:
    def test_cameras_become_pinhole_and_images_are_undistorted(self, tmp_path):
        _scene(tmp_path, CAMERAS + [("PINHOLE", [150.0, 150.0, 80.0, 60.0])])
        ds = load_colmap(tmp_path, test_every=0)
        assert len(ds) == 5 and ds.undistorters is not None and ds.undistorters[4] is None
        for i, (model, params) in enumerate(CAMERAS):
            c = ds.cameras[i]
            ref = DistortedCamera.from_colmap(model, params, W, H)
            assert (c.fx, c.fy, c.cx, c.cy) == ref.pinhole() and (c.width, c.height) == (W, H)
            assert c.cx == ref.cx and c.cy == ref.cy and 0.8 < c.fx / ref.fx < 1.2
            img = ds.load_image(i).numpy()
            x, y = _grid(W, H)
            truth = _pattern((x - c.cx) / c.fx, (y - c.cy) / c.fy)
            assert np.abs(img - truth).mean() < 4e-3  # + 8-bit quantisation of the PNG
            assert ds.load_image(i, 0.5).shape == (60, 80, 3)
        np.testing.assert_array_equal(ds.load_image(2), load_colmap(tmp_path).load_image(2))
        assert (ds.cameras[4].fx, ds.cameras[4].cx) == (150.0, 80.0)

    def test_downscaled_folder_and_max_width(self, tmp_path):
        _scene(tmp_path, CAMERAS[:2])
        _scene(tmp_path, CAMERAS[:2], scale=2, folder="images_2")
        full = load_colmap(tmp_path, test_every=0)
        half = load_colmap(tmp_path, images="images_2", test_every=0)
        for f, h in zip(full.cameras, half.cameras):
            assert (h.width, h.height) == (80, 60)
            assert h.fx == pytest.approx(f.fx / 2, rel=0.01) and (h.cx, h.cy) == (f.cx / 2, f.cy / 2)
        assert half.load_image(0).shape == (60, 80, 3)
        capped = load_colmap(tmp_path, max_width=80, test_every=0)
        c = capped.cameras[0]
        assert (c.width, c.height, c.fx) == (80, 60, full.cameras[0].fx / 2)
        assert capped.load_image(0).shape == (60, 80, 3)

    def test_undistort_false_refuses(self, tmp_path):
        _scene(tmp_path, CAMERAS[:1])
        with pytest.raises(
            ProxycodecError,
            match="cameras.txt: camera 1 uses the SIMPLE_RADIAL model with non-zero distortion.*"
            "colmap image_undistorter.*--no-undistort",
        ):
            load_colmap(tmp_path, undistort=False)

    @pytest.mark.parametrize(
        "model,params",
        [
            ("OPENCV_FISHEYE", [150.0, 150.0, 80.0, 60.0, 0.01, 0, 0, 0]),
            ("SIMPLE_RADIAL_FISHEYE", [150.0, 80.0, 60.0, 0.0]),
            ("THIN_PRISM_FISHEYE", [150.0, 150.0, 80.0, 60.0] + [0.0] * 8),
        ],
    )
    @pytest.mark.parametrize("flag", [True, False])
    def test_fisheye_is_refused(self, tmp_path, model, params, flag):
        _scene(tmp_path, [(model, params)])
        with pytest.raises(
            ProxycodecError, match=f"camera 1 uses the {model} model \\(fisheye\\).*undistort.*image_undistorter"
        ):
            load_colmap(tmp_path, undistort=flag)

    def test_fov_model_is_refused(self, tmp_path):
        _scene(tmp_path, [("FOV", [150.0, 150.0, 80.0, 60.0, 0.5])])
        with pytest.raises(ProxycodecError, match="FOV model with non-zero distortion.*image_undistorter"):
            load_colmap(tmp_path)

    def test_cli_no_undistort(self, tmp_path):
        from proxycodec.cli.main import cli

        _scene(tmp_path, CAMERAS[:1])
        r = CliRunner().invoke(cli, ["fit", str(tmp_path), "-o", str(tmp_path / "x.ply"), "--no-undistort"])
        assert r.exit_code == 2 and "non-zero distortion" in r.output, r.output
        assert not (tmp_path / "x.ply").exists()
        r = CliRunner().invoke(cli, ["eval", str(tmp_path / "missing.ply"), str(tmp_path), "--no-undistort"])
        assert "no such option" not in r.output.lower()


# ============================================================================================ (f) real data
def test_beer_is_undistorted():
    root = shared_data_path("colmap_phone/beer")
    m = read_colmap_model(root / "sparse" / "0")
    ds = load_colmap(root)
    assert len(ds) == 71 and ds.undistorters is not None and all(u is not None for u in ds.undistorters)
    by_name = {im.name: m.cameras[im.camera_id] for im in m.images}
    for c in ds.cameras:
        f, cx, cy, k = by_name[c.name].params
        assert (c.width, c.height, c.cx, c.cy) == (720, 1280, cx, cy) and c.fx == c.fy
        # a 720x1280 phone video at f = 1100..1155 with k1 in [-0.02, 0.104]: the focal moves by at most 5%
        assert 0.99 * f < c.fx < 1.05 * f and (c.fx > f) == (k > 0)
    i = ds.test_indices[1]
    img = ds.load_image(i, 0.25)
    assert img.shape == (320, 180, 3) and img.dtype == torch.float32
    assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0 and float(img.std()) > 0.05
    with pytest.raises(ProxycodecError, match="SIMPLE_RADIAL model with non-zero distortion"):
        load_colmap(root, undistort=False)
