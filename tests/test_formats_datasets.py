"""Posed-image datasets: Blender and COLMAP loaders, COLMAP bin/txt readers, lazy image loading.

Synthetic tests build tiny datasets in tmp_path; real-data tests run on every scene of ../shared/data and skip
with a clear reason when it is absent.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import shared_data_path
from PIL import Image
from proxycodec.formats.colmap import (
    CAMERA_MODELS,
    pinhole_intrinsics,
    qvec_to_rotmat,
    read_colmap_model,
    read_images_bin,
)
from proxycodec.formats.datasets import PosedImages, dataset_kind, load_blender, load_colmap, load_dataset
from proxycodec.formats.images import image_file_size, look_at_bounds

from proxycodec.camera import Camera
from proxycodec.errors import ProxycodecError

_MODEL_IDS = {name: mid for mid, (name, _) in CAMERA_MODELS.items()}


# ============================================================================================== helpers
def _project(cam: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] -> (pixel coordinates [N, 2], depth [N])."""
    Xc = X @ cam.rotation.T + cam.translation
    uv = Xc[:, :2] / Xc[:, 2:3] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    return uv, Xc[:, 2]


def _rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    w = math.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
    return np.array([w, x, y, z])


def _synthetic_model(seed: int = 0):
    """Three cameras around the origin, twelve points, tracks from their projections."""
    rng = np.random.default_rng(seed)
    cams = [
        (1, "PINHOLE", 16, 12, [14.0, 15.0, 8.0, 6.0]),
        (7, "SIMPLE_RADIAL", 16, 12, [13.0, 8.0, 6.0, 0.0]),
    ]
    eyes = [(0, -5, 1), (4, -3, 2), (-3, -4, 0.5)]
    names = ["c.png", "a.png", "b.png"]  # file order differs from name order
    ids = [10, 20, 30]
    cam_of = [1, 7, 1]
    pts = rng.uniform(-0.5, 0.5, size=(12, 3))
    images, tracks = [], [[] for _ in pts]
    for iid, eye, name, cid in zip(ids, eyes, names, cam_of):
        look = Camera.look_at(eye, (0, 0, 0), (0, 0, 1), width=16, height=12)
        q = _rotmat_to_qvec(look.rotation)
        t = look.translation
        fx, fy, cx, cy = (14.0, 15.0, 8.0, 6.0) if cid == 1 else (13.0, 13.0, 8.0, 6.0)
        K = Camera(look.world_to_camera, fx, fy, cx, cy, 16, 12)
        uv, z = _project(K, pts)
        assert (z > 0).all()
        xys = np.concatenate([uv, rng.uniform(0, 12, size=(2, 2))])  # two keypoints without a 3D point
        p3d = np.concatenate([np.arange(len(pts)) + 100, [-1, -1]]).astype(np.int64)
        for p in range(len(pts)):
            tracks[p].append((iid, p))
        images.append((iid, q, t, cid, name, xys, p3d))
    colors = rng.integers(0, 256, size=(len(pts), 3))
    points = [(100 + p, pts[p], colors[p], 0.25 * p, tracks[p]) for p in range(len(pts))]
    points[3] = (103, pts[3], colors[3], 0.5, [])  # a point with an empty track
    return cams, images, points


def _write_bin(d: Path, cams, images, points) -> None:
    d.mkdir(parents=True, exist_ok=True)
    b = struct.pack("<Q", len(cams))
    for cid, model, w, h, params in cams:
        b += struct.pack("<iiQQ", cid, _MODEL_IDS[model], w, h) + struct.pack(f"<{len(params)}d", *params)
    (d / "cameras.bin").write_bytes(b)
    b = struct.pack("<Q", len(images))
    for iid, q, t, cid, name, xys, p3d in images:
        b += struct.pack("<i4d3di", iid, *q, *t, cid) + name.encode() + b"\0" + struct.pack("<Q", len(xys))
        for (x, y), pid in zip(xys, p3d):
            b += struct.pack("<ddq", x, y, pid)
    (d / "images.bin").write_bytes(b)
    b = struct.pack("<Q", len(points))
    for pid, xyz, rgb, err, track in points:
        b += struct.pack("<Q3d3BdQ", pid, *xyz, *rgb, err, len(track))
        for iid, k in track:
            b += struct.pack("<ii", iid, k)
    (d / "points3D.bin").write_bytes(b)


def _write_txt(d: Path, cams, images, points) -> None:
    d.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", f"# Number of cameras: {len(cams)}"]
    lines += [
        f"{cid} {model} {w} {h} " + " ".join(repr(float(v)) for v in params)
        for cid, model, w, h, params in cams
    ]
    (d / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:"]
    for k, (iid, q, t, cid, name, xys, p3d) in enumerate(images):
        lines.append(f"{iid} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cid} {name}")
        if k == 0:
            lines.append("")  # an image whose keypoint line is empty still has that line
        else:
            lines.append(" ".join(f"{x!r} {y!r} {int(p)}" for (x, y), p in zip(xys.tolist(), p3d)))
    (d / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:"]
    for pid, xyz, rgb, err, track in points:
        lines.append(
            f"{pid} "
            + " ".join(repr(float(v)) for v in xyz)
            + " "
            + " ".join(str(int(c)) for c in rgb)
            + f" {err!r} "
            + " ".join(f"{i} {k}" for i, k in track)
        )
    (d / "points3D.txt").write_text("\n".join(lines) + "\n")


def _write_png(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(arr).save(path)


def _colmap_scene(root: Path, *, binary: bool = True, image_scale: int = 1, folder: str = "images"):
    cams, images, points = _synthetic_model()
    (_write_bin if binary else _write_txt)(root / "sparse" / "0", cams, images, points)
    rng = np.random.default_rng(5)
    for _, _, _, _, name, _, _ in images:
        _write_png(
            root / folder / name,
            rng.integers(0, 256, size=(12 // image_scale, 16 // image_scale, 3), dtype=np.uint8),
        )
    return cams, images, points


# ============================================================================================ COLMAP readers
class TestColmapReaders:
    def test_bin_and_txt_agree_with_the_written_model(self, tmp_path):
        cams, images, points = _synthetic_model()
        _write_bin(tmp_path / "bin", cams, images, points)
        _write_txt(tmp_path / "txt", cams, images, points)
        mb = read_colmap_model(tmp_path / "bin", keypoints=True)
        mt = read_colmap_model(tmp_path / "txt", keypoints=True)
        for m in (mb, mt):
            assert sorted(m.cameras) == [1, 7]
            assert m.cameras[7].model == "SIMPLE_RADIAL" and m.cameras[7].width == 16
            np.testing.assert_array_equal(m.cameras[1].params, [14, 15, 8, 6])
            assert [im.name for im in m.images] == ["c.png", "a.png", "b.png"]
            assert [im.camera_id for im in m.images] == [1, 7, 1]
            for im, ref in zip(m.images, images):
                np.testing.assert_array_equal(im.qvec, ref[1])
                np.testing.assert_array_equal(im.tvec, ref[2])
            np.testing.assert_array_equal(m.point_ids, [p[0] for p in points])
            np.testing.assert_array_equal(m.points, np.stack([p[1] for p in points]))
            np.testing.assert_array_equal(m.colors, np.stack([p[2] for p in points]))
            np.testing.assert_array_equal(m.errors, [p[3] for p in points])
            np.testing.assert_array_equal(np.diff(m.track_offsets), [len(p[4]) for p in points])
            np.testing.assert_array_equal(m.track_image_ids, [i for p in points for i, _ in p[4]])
            np.testing.assert_array_equal(m.track_point2d_idx, [k for p in points for _, k in p[4]])
        assert [im.num_points2d for im in mb.images] == [14, 14, 14]
        assert [im.num_points2d for im in mt.images] == [0, 14, 14]  # the first keypoint line was left empty
        for a, b in zip(mb.images[1:], mt.images[1:]):
            np.testing.assert_array_equal(a.xys, b.xys)
            np.testing.assert_array_equal(a.point3d_ids, b.point3d_ids)
        assert read_images_bin(tmp_path / "bin" / "images.bin")[0].xys is None

    def test_keypoints_are_projections_of_their_points(self, tmp_path):
        cams, images, points = _synthetic_model()
        _write_bin(tmp_path, cams, images, points)
        m = read_colmap_model(tmp_path, keypoints=True)
        for im in m.images:
            fx, fy, cx, cy = pinhole_intrinsics(m.cameras[im.camera_id])
            cam = Camera(im.world_to_camera, fx, fy, cx, cy, 16, 12)
            uv, z = _project(cam, m.points)
            ok = im.point3d_ids >= 0
            idx = np.searchsorted(m.point_ids, im.point3d_ids[ok])
            np.testing.assert_allclose(uv[idx], im.xys[ok], atol=1e-9)

    def test_qvec_to_rotmat(self):
        R = qvec_to_rotmat([math.cos(0.3), 0, 0, math.sin(0.3)])  # 0.6 rad about z
        np.testing.assert_allclose(
            R, [[math.cos(0.6), -math.sin(0.6), 0], [math.sin(0.6), math.cos(0.6), 0], [0, 0, 1]], atol=1e-12
        )
        np.testing.assert_allclose(qvec_to_rotmat([2, 0, 0, 0]), np.eye(3))
        with pytest.raises(ProxycodecError, match="zero"):
            qvec_to_rotmat([0, 0, 0, 0])

    def test_truncated_and_absurd_binaries(self, tmp_path):
        cams, images, points = _synthetic_model()
        _write_bin(tmp_path, cams, images, points)
        for name in ("cameras.bin", "images.bin", "points3D.bin"):
            raw = (tmp_path / name).read_bytes()
            (tmp_path / name).write_bytes(raw[:-3])
            with pytest.raises(ProxycodecError, match="truncated|more than") as e:
                read_colmap_model(tmp_path)
            assert name in str(e.value)
            (tmp_path / name).write_bytes(raw + b"\0")
            with pytest.raises(ProxycodecError, match="unexpected bytes") as e:
                read_colmap_model(tmp_path)
            assert name in str(e.value)
            (tmp_path / name).write_bytes(struct.pack("<Q", 1 << 50) + raw[8:])
            with pytest.raises(ProxycodecError, match="declares 1125899906842624"):
                read_colmap_model(tmp_path)
            (tmp_path / name).write_bytes(raw)
        raw = (tmp_path / "points3D.bin").read_bytes()
        # first point's track length -> huge
        bad = raw[: 8 + 43] + struct.pack("<Q", 1 << 40) + raw[8 + 51 :]
        (tmp_path / "points3D.bin").write_bytes(bad)
        with pytest.raises(ProxycodecError, match="track of 1099511627776"):
            read_colmap_model(tmp_path)

    def test_text_errors(self, tmp_path):
        cams, images, points = _synthetic_model()
        _write_txt(tmp_path, cams, images, points)
        (tmp_path / "cameras.txt").write_text("1 PINHOLE 16 12 1 2 3\n")
        with pytest.raises(ProxycodecError, match="needs 4 parameters"):
            read_colmap_model(tmp_path)
        (tmp_path / "cameras.txt").write_text("1 WEIRD 16 12 1 2 3\n")
        with pytest.raises(ProxycodecError, match="unknown camera model 'WEIRD'"):
            read_colmap_model(tmp_path)

    @pytest.mark.parametrize(
        "model,params,ok",
        [
            ("SIMPLE_PINHOLE", [10, 8, 6], True),
            ("SIMPLE_RADIAL", [10, 8, 6, 0.0], True),
            ("RADIAL", [10, 8, 6, 0, 0], True),
            ("OPENCV", [10, 11, 8, 6, 0, 0, 0, 0], True),
            ("FULL_OPENCV", [10, 11, 8, 6] + [0] * 8, True),
            ("SIMPLE_RADIAL", [10, 8, 6, 0.01], False),
            ("OPENCV", [10, 11, 8, 6, 0, 0, 1e-4, 0], False),
            ("OPENCV_FISHEYE", [10, 11, 8, 6, 0, 0, 0, 0], False),
        ],
    )
    def test_pinhole_intrinsics(self, model, params, ok):
        from proxycodec.formats.colmap import ColmapCamera

        cam = ColmapCamera(3, model, 16, 12, np.array(params, dtype=np.float64))
        if ok:
            fx, fy, cx, cy = pinhole_intrinsics(cam)
            assert (fx, cx, cy) == (10, 8, 6) and fy in (10, 11)
        else:
            with pytest.raises(
                ProxycodecError, match=f"camera 3 uses the {model} model.*undistort.*image_undistorter"
            ):
                pinhole_intrinsics(cam)


# =========================================================================================== COLMAP datasets
class TestLoadColmap:
    @pytest.mark.parametrize("binary", [True, False])
    def test_cameras_split_and_images(self, tmp_path, binary):
        _colmap_scene(tmp_path, binary=binary)
        ds = load_colmap(tmp_path, test_every=2)
        assert dataset_kind(tmp_path) == "colmap"
        assert [c.name for c in ds.cameras] == ["a.png", "b.png", "c.png"]
        assert ds.test_indices == [0, 2] and ds.train_indices == [1]
        a = ds.cameras[0]  # camera 7: SIMPLE_RADIAL with k = 0
        assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (13, 13, 8, 6, 16, 12)
        assert ds.points.shape == (12, 3) and ds.points.dtype == np.float32
        assert ds.point_colors.dtype == np.uint8
        assert ds.background == (0.0, 0.0, 0.0)
        assert (ds.bounds[0] <= ds.points.min(0) + 0.02).all() and (
            ds.bounds[1] >= ds.points.max(0) - 0.02
        ).all()
        # every point projects inside every image, in front of the camera
        for cam in ds.cameras:
            uv, z = _project(cam, ds.points.astype(np.float64))
            assert (z > 0).all() and (uv >= 0).all() and (uv[:, 0] <= 16).all() and (uv[:, 1] <= 12).all()
        img = ds.load_image(1)
        raw = np.asarray(Image.open(tmp_path / "images" / "b.png"), dtype=np.float32) / 255
        np.testing.assert_allclose(img.numpy(), raw, atol=1e-6)
        assert ds.load_image(1, 0.5).shape == (6, 8, 3)
        assert load_colmap(tmp_path, test_every=0).test_indices == []
        assert len(load_dataset(tmp_path).test_indices) == 1

    def test_downscaled_image_folder_scales_intrinsics(self, tmp_path):
        _colmap_scene(tmp_path)
        _colmap_scene(tmp_path, image_scale=2, folder="images_2")
        full = load_colmap(tmp_path)
        half = load_colmap(tmp_path, images="images_2")
        for f, h in zip(full.cameras, half.cameras):
            assert (h.width, h.height) == (8, 6)
            assert (h.fx, h.fy, h.cx, h.cy) == (f.fx / 2, f.fy / 2, f.cx / 2, f.cy / 2)
            np.testing.assert_array_equal(h.world_to_camera, f.world_to_camera)
        assert half.load_image(0).shape == (6, 8, 3)
        capped = load_colmap(tmp_path, max_width=8)
        assert [(c.width, c.height, c.fx) for c in capped.cameras] == [(8, 6, 6.5), (8, 6, 7.0), (8, 6, 7.0)]
        assert capped.load_image(0).shape == (6, 8, 3)

    def test_errors(self, tmp_path):
        cams, images, points = _colmap_scene(tmp_path)
        (tmp_path / "images" / "b.png").unlink()
        with pytest.raises(ProxycodecError, match="b.png: image file not found"):
            load_colmap(tmp_path)
        _write_png(tmp_path / "images" / "b.png", np.zeros((12, 5, 3), np.uint8))
        with pytest.raises(ProxycodecError, match="b.png: image is 5x12 but its COLMAP camera 1 is 16x12"):
            load_colmap(tmp_path)
        with pytest.raises(ProxycodecError, match="image folder 'images_8' not found"):
            load_colmap(tmp_path, images="images_8")
        cams[1] = (7, "OPENCV", 16, 12, [13.0, 13.0, 8.0, 6.0, 0.1, 0, 0, 0])
        _write_bin(tmp_path / "sparse" / "0", cams, images, points)
        with pytest.raises(
            ProxycodecError,
            match="cameras.bin: camera 7 uses the OPENCV model with non-zero "
            "distortion.*colmap image_undistorter",
        ):
            load_colmap(tmp_path, undistort=False)  # the default undistorts: test_formats_undistort.py
        with pytest.raises(ProxycodecError, match="no COLMAP model"):
            load_colmap(tmp_path / "images")
        with pytest.raises(ProxycodecError, match="not a dataset"):
            dataset_kind(tmp_path / "images")

    def test_image_changed_on_disk_is_detected(self, tmp_path):
        _colmap_scene(tmp_path)
        ds = load_colmap(tmp_path)
        _write_png(tmp_path / "images" / "a.png", np.zeros((6, 8, 3), np.uint8))
        with pytest.raises(ProxycodecError, match="a.png: image is 8x6 but the dataset expects 16x12"):
            ds.load_image(0)
        (tmp_path / "images" / "a.png").unlink()
        with pytest.raises(ProxycodecError, match="a.png: image file not found"):
            ds.load_image(0)


# ============================================================================================== Blender
def _blender_scene(root: Path, *, w: int = 20, h: int = 10, angle: float = 1.0, with_test: bool = True):
    """Two train frames and one test frame, all looking at the origin; RGBA images with known content."""
    rng = np.random.default_rng(3)
    eyes = {"train": [(0, -4, 1), (3, -2, 2)], "test": [(-2, -3, -1)]}
    for split in ("train", "test") if with_test else ("train",):
        frames = []
        for k, eye in enumerate(eyes[split]):
            w2c = Camera.look_at(eye, (0, 0, 0), (0, 0, 1), width=w, height=h).world_to_camera
            c2w = np.linalg.inv(w2c)
            c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL axes
            frames.append(
                {"file_path": f"./{split}/r_{k}", "rotation": 0.0, "transform_matrix": c2w.tolist()}
            )
            img = rng.integers(0, 256, size=(h, w, 4), dtype=np.uint8)
            img[:2, :2] = (255, 0, 0, 128)  # half-transparent red corner block
            img[:2, 2:4] = (10, 20, 30, 0)  # fully transparent block
            img[2:4, :4] = (40, 80, 120, 255)  # opaque block
            _write_png(root / split / f"r_{k}.png", img)
        (root / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": angle, "frames": frames})
        )


class TestBlender:
    def test_cameras_and_split(self, tmp_path):
        _blender_scene(tmp_path)
        ds = load_blender(tmp_path)
        assert dataset_kind(tmp_path) == "blender" and ds.kind == "blender"
        assert len(ds) == 3 and ds.train_indices == [0, 1] and ds.test_indices == [2]
        assert [c.name for c in ds.cameras] == ["train/r_0", "train/r_1", "test/r_0"]
        f = 0.5 * 20 / math.tan(0.5)
        for cam in ds.cameras:
            assert (cam.width, cam.height, cam.cx, cam.cy) == (20, 10, 10, 5)
            assert cam.fx == pytest.approx(f) and cam.fy == pytest.approx(f)
            uv, z = _project(cam, np.zeros((1, 3)))  # the object centre projects to the image centre
            assert z[0] > 0
            np.testing.assert_allclose(uv[0], [10, 5], atol=1e-9)
        eye = Camera.look_at((0, -4, 1), (0, 0, 0), (0, 0, 1), width=20, height=10)
        np.testing.assert_allclose(ds.cameras[0].world_to_camera, eye.world_to_camera, atol=1e-12)
        assert ds.points is None and ds.point_colors is None and ds.background == (1.0, 1.0, 1.0)
        np.testing.assert_allclose(ds.bounds.mean(0), 0, atol=1e-9)
        assert 0.5 < ds.bounds[1, 0] < 4

    def test_alpha_compositing_is_exact(self, tmp_path):
        _blender_scene(tmp_path)
        ds = load_blender(tmp_path, background=(0.0, 0.0, 1.0))
        img = ds.load_image(0).numpy()
        assert img.shape == (10, 20, 3) and img.dtype == np.float32
        a = 128 / 255
        np.testing.assert_allclose(img[0, 0], [a, 0, 1 - a], atol=1e-6)
        np.testing.assert_allclose(img[0, 2], [0, 0, 1], atol=1e-6)
        np.testing.assert_allclose(img[2, 0], [40 / 255, 80 / 255, 120 / 255], atol=1e-6)
        raw = np.asarray(Image.open(tmp_path / "train" / "r_0.png"), dtype=np.float64) / 255
        expect = raw[..., :3] * raw[..., 3:] + np.array([0, 0, 1]) * (1 - raw[..., 3:])
        np.testing.assert_allclose(img, expect, atol=1e-6)
        # xi = 0.5 is an exact 2x2 area average of the composited image
        small = ds.load_image(0, 0.5).numpy()
        assert small.shape == (5, 10, 3)
        np.testing.assert_allclose(small, expect.reshape(5, 2, 10, 2, 3).mean((1, 3)), atol=1e-5)
        np.testing.assert_allclose(small[0, 0], [a, 0, 1 - a], atol=1e-6)
        assert ds.load_image(0, 0.025).shape == (1, 1, 3)  # round(0.5) = 0 -> at least one pixel
        big = ds.load_image(0, 2.0)
        assert big.shape == (20, 40, 3) and float(big.min()) >= 0 and float(big.max()) <= 1

    def test_load_image_is_lazy_cached_and_returns_fresh_tensors(self, tmp_path):
        _blender_scene(tmp_path)
        ds = load_blender(tmp_path)
        assert ds._cache.nbytes == 0  # nothing decoded at load time
        a = ds.load_image(1)
        a.zero_()
        b = ds.load_image(1)
        assert float(b.sum()) > 0
        assert ds._cache.nbytes == 10 * 20 * 3 * 4
        tiny = load_blender(tmp_path, cache_bytes=0)
        torch.testing.assert_close(tiny.load_image(2, 0.3), ds.load_image(2, 0.3))
        assert tiny._cache.nbytes == 0
        with pytest.raises(ProxycodecError, match="outside"):
            ds.load_image(0, 3.0)
        with pytest.raises(ProxycodecError, match="out of range"):
            ds.load_image(3)

    def test_max_width(self, tmp_path):
        _blender_scene(tmp_path)
        ds = load_blender(tmp_path, max_width=10)
        full = load_blender(tmp_path)
        for c, f in zip(ds.cameras, full.cameras):
            assert (c.width, c.height) == (10, 5)
            assert c.fx == pytest.approx(f.fx / 2) and c.cx == 5 and c.cy == 2.5
        assert ds.load_image(0).shape == (5, 10, 3)
        torch.testing.assert_close(ds.load_image(0), full.load_image(0, 0.5))
        assert ds.file_sizes == [(20, 10)] * 3
        assert load_blender(tmp_path, max_width=100).cameras[0].width == 20

    def test_no_test_file_and_explicit_extension(self, tmp_path):
        _blender_scene(tmp_path, with_test=False)
        meta = json.loads((tmp_path / "transforms_train.json").read_text())
        meta["frames"][1]["file_path"] = "./train/r_1.png"
        (tmp_path / "transforms_train.json").write_text(json.dumps(meta))
        ds = load_blender(tmp_path)
        assert ds.test_indices == [] and len(ds) == 2
        assert ds.cameras[1].image_path.endswith("r_1.png")

    def test_errors(self, tmp_path):
        _blender_scene(tmp_path)
        (tmp_path / "test" / "r_0.png").unlink()
        with pytest.raises(ProxycodecError, match=r"test/r_0.png: image file not found"):
            load_blender(tmp_path)
        meta = json.loads((tmp_path / "transforms_train.json").read_text())
        (tmp_path / "transforms_test.json").unlink()
        for bad, match in [
            ({**meta, "camera_angle_x": "wide"}, "camera_angle_x"),
            ({**meta, "frames": {}}, "'frames' must be a list"),
            (
                {**meta, "frames": [{"file_path": "./train/r_0", "transform_matrix": [[1, 2]]}]},
                "frame 0: transform_matrix must be a finite 4x4",
            ),
        ]:
            (tmp_path / "transforms_train.json").write_text(json.dumps(bad))
            with pytest.raises(ProxycodecError, match=match) as e:
                load_blender(tmp_path)
            assert "transforms_train.json" in str(e.value)
        (tmp_path / "transforms_train.json").write_text("{not json")
        with pytest.raises(ProxycodecError, match="transforms_train.json: invalid JSON"):
            load_blender(tmp_path)
        with pytest.raises(ProxycodecError, match="transforms_train.json is missing"):
            load_blender(tmp_path / "train")
        with pytest.raises(ProxycodecError, match="folder not found"):
            load_blender(tmp_path / "nope")

    def test_image_file_size_reads_headers_only(self, tmp_path):
        _write_png(tmp_path / "x.png", np.zeros((7, 9, 4), np.uint8))
        Image.fromarray(np.zeros((5, 3, 3), np.uint8)).save(tmp_path / "y.jpg")
        assert image_file_size(tmp_path / "x.png") == (9, 7)
        assert image_file_size(tmp_path / "y.jpg") == (3, 5)
        (tmp_path / "z.png").write_bytes(b"garbage")
        with pytest.raises(ProxycodecError, match="z.png: cannot read image header"):
            image_file_size(tmp_path / "z.png")

    def test_posed_images_validation(self, tmp_path):
        cam = Camera(np.eye(4), 10, 10, 5, 5, 10, 10, image_path=str(tmp_path / "x.png"))
        with pytest.raises(ProxycodecError, match="distinct"):
            PosedImages([cam], [0], [0], None, None, np.zeros((2, 3)), (1, 1, 1), [(10, 10)])
        with pytest.raises(ProxycodecError, match="background"):
            PosedImages([cam], [0], [], None, None, np.zeros((2, 3)), (2, 1, 1), [(10, 10)])
        with pytest.raises(ProxycodecError, match="background"):
            PosedImages([cam], [0], [], None, None, np.zeros((2, 3)), (float("nan"), 1, 1), [(10, 10)])
        with pytest.raises(ProxycodecError, match="bounds"):
            PosedImages([cam], [0], [], None, None, np.zeros((3, 3)), (1, 1, 1), [(10, 10)])
        with pytest.raises(ProxycodecError, match="cameras"):
            look_at_bounds([])


# ============================================================================================== real data
_REAL: dict[str, PosedImages] = {}


def _real(scene: str, **kw) -> PosedImages:
    key = scene + repr(sorted(kw.items()))
    if key not in _REAL:
        root = shared_data_path(scene)
        _REAL[key] = (
            load_blender(root, **kw) if scene.startswith("nerf_synthetic") else load_colmap(root, **kw)
        )
    return _REAL[key]


# scene, image size, focal, train frame 0 camera centre (values from shared/data/README.md)
_BLENDER_SCENES = [
    ("nerf_synthetic/lego", 800, 1111.111, (-0.0538, 3.8455, 1.2081)),
    ("nerf_synthetic/mic", 400, 555.556, (1.1453, 2.7771, 2.6882)),
]


@pytest.mark.parametrize("scene,size,focal,center0", _BLENDER_SCENES)
class TestRealBlender:
    def test_counts_and_intrinsics(self, scene, size, focal, center0):
        ds = _real(scene)
        assert len(ds) == 125 and len(ds.train_indices) == 100 and len(ds.test_indices) == 25
        assert ds.cameras[0].name == "train/r_0" and ds.cameras[100].name == "test/r_0"
        assert ds.cameras[-1].name == "test/r_192"
        for cam in ds.cameras:
            assert (cam.width, cam.height) == (size, size)
            assert cam.fx == pytest.approx(focal, abs=1e-3) and cam.fy == cam.fx
            assert np.linalg.norm(cam.center) == pytest.approx(4.0311, abs=1e-3)
        # the object centre (origin) projects to the image centre in every view
        for cam in ds.cameras:
            uv, z = _project(cam, np.zeros((1, 3)))
            assert z[0] > 0
            np.testing.assert_allclose(uv[0], [size / 2, size / 2], atol=0.01 * size)
        np.testing.assert_allclose(ds.cameras[0].center, center0, atol=1e-4)
        np.testing.assert_allclose(ds.cameras[100].center, [0.0, 2.7373, 2.9593], atol=1e-4)  # same test path
        lo, hi = ds.bounds
        assert (lo < -1).all() and (hi > 1).all() and (hi < 1.6).all() and (lo > -1.6).all()

    def test_load_images(self, scene, size, focal, center0):
        ds = _real(scene)
        img = ds.load_image(0)
        assert img.shape == (size, size, 3) and img.dtype == torch.float32
        assert float(img.min()) >= 0 and float(img.max()) <= 1
        # most pixels are transparent in the PNG -> white after compositing
        assert float((img == 1).all(-1).float().mean()) > 0.5
        assert ds.load_image(len(ds) - 1, 0.1).shape == (size // 10, size // 10, 3)
        black = load_blender(shared_data_path(scene), background=(0, 0, 0))
        assert float(black.load_image(0)[0, 0].sum()) == 0

    def test_max_width_400(self, scene, size, focal, center0):
        ds = _real(scene, max_width=400)
        for cam in ds.cameras:
            assert (cam.width, cam.height) == (400, 400)
            assert cam.fx == pytest.approx(focal * 400 / size, abs=1e-3)
        assert ds.load_image(5).shape == (400, 400, 3)


class TestRealColmap:
    def test_bonsai_counts(self):
        ds = _real("mipnerf360/bonsai")
        assert len(ds) == 292 and len(ds.train_indices) == 255 and len(ds.test_indices) == 37
        names = [c.name for c in ds.cameras]
        assert names == sorted(names) and names[0] == "DSCF5565.JPG" and names[-1] == "DSCF5856.JPG"
        assert [names[i] for i in ds.test_indices] == names[::8]
        # the model rebuilt on 2026-11-26 (../shared/data/README.md, "Bonsai poses"): 292 distinct camera centres
        assert ds.points.shape == (109939, 3) and ds.point_colors.shape == (109939, 3)
        assert ds.point_colors.dtype == np.uint8
        for cam in ds.cameras:
            assert (cam.width, cam.height) == (800, 533)
            assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx(
                (824.8373, 825.7687, 400.0, 266.5), abs=1e-3
            )
        centers = np.stack([c.center for c in ds.cameras])
        np.testing.assert_allclose(centers.mean(0), [0.0169, 0.0762, 0.0408], atol=2e-3)
        assert len(np.unique(np.round(centers, 6), axis=0)) == 292  # the old model had 101 cameras at one centre
        assert (ds.bounds[0] < centers.mean(0)).all() and (ds.bounds[1] > centers.mean(0)).all()

    def test_bonsai_model_and_projection(self):
        root = shared_data_path("mipnerf360/bonsai")
        m = read_colmap_model(root / "sparse" / "0", keypoints=True)
        assert [(c.model, c.width, c.height) for c in m.cameras.values()] == [("PINHOLE", 800, 533)]
        assert len(m.images) == 292 and m.points.shape == (109939, 3)
        assert int(m.track_offsets[-1]) == 837706  # observations: mean track length 7.62, as the data README says
        assert np.mean([im.num_points2d for im in m.images]) == pytest.approx(5383, abs=1)
        ds = _real("mipnerf360/bonsai")
        by_name = {c.name: c for c in ds.cameras}
        by_id = {im.id: im for im in m.images}
        rng = np.random.default_rng(0)
        checked = 0
        for p in rng.choice(len(m.points), size=20, replace=False):
            s, e = m.track_offsets[p], m.track_offsets[p + 1]
            for iid, k in zip(m.track_image_ids[s:e][:5], m.track_point2d_idx[s:e][:5]):
                im = by_id[int(iid)]
                cam = by_name[im.name]
                uv, z = _project(cam, m.points[p : p + 1])
                assert z[0] > 0
                assert 0 <= uv[0, 0] <= cam.width and 0 <= uv[0, 1] <= cam.height
                assert im.point3d_ids[k] == m.point_ids[p]
                assert (
                    np.linalg.norm(uv[0] - im.xys[k]) < 4 + 4 * m.errors[p]
                )  # mean reprojection error is 0.39 px
                checked += 1
        assert checked >= 20

    def test_bonsai_images(self):
        ds = _real("mipnerf360/bonsai")
        img = ds.load_image(ds.test_indices[1])
        assert img.shape == (533, 800, 3) and float(img.min()) >= 0 and float(img.max()) <= 1
        assert ds.load_image(0, 0.1).shape == (53, 80, 3)
        capped = _real("mipnerf360/bonsai", max_width=400)
        c = capped.cameras[0]
        assert (
            c.width == 400 and c.height == round(533 * 0.5) and c.fx == pytest.approx(824.8373 / 2, abs=1e-3)
        )
        assert capped.load_image(0).shape == (c.height, 400, 3)

    def test_beer_needs_undistortion(self):
        root = shared_data_path("colmap_phone/beer")
        with pytest.raises(
            ProxycodecError,
            match="cameras.bin: camera \\d+ uses the SIMPLE_RADIAL model with "
            "non-zero distortion.*undistort.*colmap image_undistorter",
        ):
            load_colmap(root, undistort=False)  # by default it is undistorted: tests/test_formats_undistort.py
        m = read_colmap_model(root / "sparse" / "0")
        assert len(m.cameras) == 71 and {c.model for c in m.cameras.values()} == {"SIMPLE_RADIAL"}
        assert {(c.width, c.height) for c in m.cameras.values()} == {(720, 1280)}
        assert len(m.images) == 71 and m.points.shape == (4414, 3)
        assert m.images[0].name.endswith(".jpg")
