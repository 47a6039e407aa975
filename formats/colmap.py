"""COLMAP sparse models (``cameras``, ``images``, ``points3D`` as ``.bin`` or ``.txt``) and COLMAP datasets.

The binary readers follow COLMAP's ``src/colmap/scene/reconstruction_io.cc`` (all little-endian):

* ``cameras.bin``: u64 n; n x (i32 camera_id, i32 model_id, u64 width, u64 height, f64 params[model]).
* ``images.bin``: u64 n; n x (i32 image_id, f64 qvec[4] (w, x, y, z), f64 tvec[3], i32 camera_id,
  NUL-terminated name, u64 n2d, n2d x (f64 x, f64 y, i64 point3D_id)).
* ``points3D.bin``: u64 n; n x (u64 point3D_id, f64 xyz[3], u8 rgb[3], f64 error, u64 track_length,
  track_length x (i32 image_id, i32 point2D_idx)).

Every count is bounded by the bytes actually left in the file before anything is allocated. The 2D
keypoints of ``images.bin`` (most of its bytes) are skipped with a seek unless asked for; the variable-length
point records are located with one scan over their track lengths and then gathered with vectorised numpy
indexing.

``world_to_camera`` is ``[R(qvec) | tvec]``, COLMAP's camera convention (x right, y down, z forward), which is
also :class:`~proxycodec.camera.Camera`'s. COLMAP's pixel-centre convention (the top-left pixel's centre is at
(0.5, 0.5)) is Camera's too, so principal points are used as stored.
"""

from __future__ import annotations

import mmap
import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import ProxycodecError
from .images import DEFAULT_CACHE_BYTES, PosedImages, image_file_size, look_at_bounds
from .undistort import UNDISTORTABLE_MODELS, DistortedCamera, RemapCache, Undistorter

__all__ = [
    "CAMERA_MODELS",
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "read_colmap_model",
    "read_cameras_bin",
    "read_cameras_txt",
    "read_images_bin",
    "read_images_txt",
    "read_points3d_bin",
    "read_points3d_txt",
    "qvec_to_rotmat",
    "pinhole_intrinsics",
    "load_colmap",
    "find_sparse_dir",
]

#: model id -> (name, number of parameters), as in COLMAP's sensor/models.h.
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_MODEL_BY_NAME = {name: (mid, n) for mid, (name, n) in CAMERA_MODELS.items()}

#: Radial (non-fisheye) models: with every distortion coefficient exactly 0 they ARE pinhole cameras.
#: name -> (index of fx, index of fy (same as fx for single-focal models), index of cx, index of cy).
_PINHOLE_LIKE = {
    "SIMPLE_PINHOLE": (0, 0, 1, 2),
    "PINHOLE": (0, 1, 2, 3),
    "SIMPLE_RADIAL": (0, 0, 1, 2),
    "RADIAL": (0, 0, 1, 2),
    "OPENCV": (0, 1, 2, 3),
    "FULL_OPENCV": (0, 1, 2, 3),
    "FOV": (0, 1, 2, 3),
}

#: Largest text model file we parse (text models are for small scenes; big ones come as .bin).
_MAX_TEXT_BYTES = 2 * 1024 * 1024 * 1024


@dataclass(frozen=True, eq=False)
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # [n_params] float64


@dataclass(frozen=True, eq=False)
class ColmapImage:
    id: int
    qvec: np.ndarray  # [4] float64, (w, x, y, z), world -> camera rotation
    tvec: np.ndarray  # [3] float64, world -> camera translation
    camera_id: int
    name: str
    num_points2d: int
    xys: np.ndarray | None = None  # [n2d, 2] float64 keypoints, only when read with keypoints=True
    point3d_ids: np.ndarray | None = None  # [n2d] int64 (-1: no 3D point), only with keypoints=True

    @property
    def world_to_camera(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = qvec_to_rotmat(self.qvec)
        m[:3, 3] = self.tvec
        return m


@dataclass(frozen=True, eq=False)
class ColmapModel:
    """A sparse reconstruction. Point tracks are stored CSR-style: the observations of point p are
    ``track_image_ids[track_offsets[p]:track_offsets[p+1]]`` (and ``track_point2d_idx`` alike)."""

    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]  # in file order
    point_ids: np.ndarray  # [P] int64
    points: np.ndarray  # [P, 3] float64
    colors: np.ndarray  # [P, 3] uint8
    errors: np.ndarray  # [P] float64 mean reprojection error
    track_offsets: np.ndarray  # [P+1] int64
    track_image_ids: np.ndarray  # [T] int32
    track_point2d_idx: np.ndarray  # [T] int32


def qvec_to_rotmat(q: Sequence[float]) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> rotation matrix [3, 3] (normalised first)."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ProxycodecError(f"quaternion {q.tolist()} is zero or not finite")
    w, x, y, z = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _valid_pose(q: np.ndarray, t: np.ndarray) -> bool:
    """Finite translation and a quaternion whose norm is finite and not ~0 (so it can be normalised)."""
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        return False
    with np.errstate(over="ignore"):
        n = float(np.linalg.norm(q))
    return bool(np.isfinite(n) and n >= 1e-12)


# -------------------------------------------------------------------------------------- binary reading
class _Bin:
    """Bounded little-endian reader over a memory-mapped (or in-memory) file."""

    def __init__(self, path: Path):
        self.path = path
        try:
            fh = open(path, "rb")
        except FileNotFoundError:
            raise ProxycodecError("file not found", path) from None
        with fh:
            self.size = os.fstat(fh.fileno()).st_size
            if self.size == 0:
                raise ProxycodecError("file is empty", path)
            self.buf = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        self.pos = 0

    def close(self) -> None:
        self.buf.close()

    def need(self, n: int, what: str) -> None:
        if n < 0 or self.pos + n > self.size:
            raise ProxycodecError(
                f"file is truncated while reading {what} (needs {n} bytes at offset "
                f"{self.pos}, file has {self.size})",
                self.path,
            )

    def unpack(self, st: struct.Struct, what: str) -> tuple:
        self.need(st.size, what)
        v = st.unpack_from(self.buf, self.pos)
        self.pos += st.size
        return v

    def count(self, min_record: int, what: str) -> int:
        (n,) = self.unpack(_U64, f"the number of {what}")
        if n * min_record > self.size - self.pos:
            raise ProxycodecError(f"declares {n} {what}, more than its {self.size} bytes can hold", self.path)
        return int(n)

    def cstring(self, what: str) -> str:
        end = self.buf.find(b"\0", self.pos, min(self.size, self.pos + 65536))
        if end < 0:
            raise ProxycodecError(f"unterminated {what}", self.path)
        raw = self.buf[self.pos : end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise ProxycodecError(f"{what} is not valid UTF-8", self.path) from None

    def finish(self) -> None:
        if self.pos != self.size:
            raise ProxycodecError(f"{self.size - self.pos} unexpected bytes after the last record", self.path)


_U64 = struct.Struct("<Q")
_CAM = struct.Struct("<iiQQ")
_IMG = struct.Struct("<i4d3di")
_PT_HEAD = 51  # u64 id, 3 f64, 3 u8, f64 error, u64 track length
_PT_DTYPE = np.dtype(
    [("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"), ("track_length", "<u8")]
)
assert _PT_DTYPE.itemsize == _PT_HEAD


def read_cameras_bin(path: str | os.PathLike) -> dict[int, ColmapCamera]:
    r = _Bin(Path(path))
    try:
        n = r.count(_CAM.size + 8 * 3, "cameras")
        cams: dict[int, ColmapCamera] = {}
        for _ in range(n):
            cid, mid, w, h = r.unpack(_CAM, "a camera record")
            if mid not in CAMERA_MODELS:
                raise ProxycodecError(f"camera {cid} has unknown camera model id {mid}", path)
            name, nparams = CAMERA_MODELS[mid]
            params = np.array(r.unpack(struct.Struct(f"<{nparams}d"), f"the parameters of camera {cid}"))
            cams[cid] = _make_camera(path, cid, name, w, h, params)
        r.finish()
        return cams
    finally:
        r.close()


def _make_camera(path, cid: int, model: str, w: int, h: int, params: np.ndarray) -> ColmapCamera:
    if not (1 <= w <= 1 << 20 and 1 <= h <= 1 << 20):
        raise ProxycodecError(f"camera {cid} has an implausible size {w}x{h}", path)
    if not np.isfinite(params).all():
        raise ProxycodecError(f"camera {cid} has non-finite parameters", path)
    return ColmapCamera(int(cid), model, int(w), int(h), params)


def read_images_bin(path: str | os.PathLike, *, keypoints: bool = False) -> list[ColmapImage]:
    """Registered images; their 2D keypoints are skipped unless ``keypoints``."""
    r = _Bin(Path(path))
    try:
        n = r.count(_IMG.size + 1 + 8, "images")
        images: list[ColmapImage] = []
        for _ in range(n):
            iid, qw, qx, qy, qz, tx, ty, tz, cid = r.unpack(_IMG, "an image record")
            name = r.cstring(f"the name of image {iid}")
            (n2d,) = r.unpack(_U64, f"the keypoint count of image {iid}")
            r.need(24 * n2d, f"the {n2d} keypoints of image {iid}")
            xys = ids = None
            if keypoints:
                kp = np.frombuffer(
                    r.buf, dtype=np.dtype([("xy", "<f8", (2,)), ("id", "<i8")]), count=n2d, offset=r.pos
                )
                xys, ids = kp["xy"].copy(), kp["id"].copy()
                del kp  # release the view of the mapping before it is closed
            r.pos += 24 * n2d
            q, t = np.array([qw, qx, qy, qz]), np.array([tx, ty, tz])
            if not _valid_pose(q, t):
                raise ProxycodecError(f"image {iid} ({name!r}) has an invalid pose", path)
            images.append(ColmapImage(int(iid), q, t, int(cid), name, int(n2d), xys, ids))
        r.finish()
        return images
    finally:
        r.close()


def _gather_bytes(u8: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """Rows of ``width`` bytes at ``starts`` -> uint8 [len(starts), width] (a vectorised copy per column)."""
    out = np.empty((starts.shape[0], width), np.uint8)
    for b in range(width):
        out[:, b] = u8[starts + b]
    return out


def read_points3d_bin(path: str | os.PathLike) -> tuple[np.ndarray, ...]:
    """(ids [P] i64, xyz [P,3] f64, rgb [P,3] u8, error [P] f64, track_offsets [P+1] i64,
    track_image_ids [T] i32, track_point2d_idx [T] i32)."""
    r = _Bin(Path(path))
    try:
        n = r.count(_PT_HEAD, "points")
        # The only per-record loop: records have variable length, so their offsets need a sequential scan of
        # track lengths (one 8-byte read per point).
        starts = [0] * n
        lengths = [0] * n
        pos, size, buf = r.pos, r.size, r.buf
        unpack = _U64.unpack_from
        for i in range(n):
            if pos + _PT_HEAD > size:
                r.pos = pos
                r.need(_PT_HEAD, f"point record {i}")
            (tl,) = unpack(buf, pos + 43)
            starts[i] = pos
            lengths[i] = tl
            pos += _PT_HEAD + 8 * tl
            if pos > size:
                raise ProxycodecError(
                    f"point record {i} declares a track of {tl} observations, more than the file holds", path
                )
        r.pos = pos
        r.finish()
        u8 = np.frombuffer(buf, dtype=np.uint8)
        try:
            st = np.asarray(starts, dtype=np.int64)
            ln = np.asarray(lengths, dtype=np.int64)
            rec = _gather_bytes(u8, st, _PT_HEAD).view(_PT_DTYPE).reshape(n)
            offsets = np.zeros(n + 1, np.int64)
            np.cumsum(ln, out=offsets[1:])
            total = int(offsets[-1])
            # byte position of observation k of point p: start_p + 51 + 8 * k
            obs_start = np.repeat(st + _PT_HEAD - 8 * offsets[:-1], ln) + 8 * np.arange(total, dtype=np.int64)
            obs = _gather_bytes(u8, obs_start, 8).view("<i4").reshape(total, 2)
            ids = rec["id"].astype(np.int64)
            xyz = rec["xyz"].astype(np.float64)
            rgb = rec["rgb"].copy()
            err = rec["error"].astype(np.float64)
            img_ids = obs[:, 0].copy()
            p2d = obs[:, 1].copy()
        finally:
            del u8
        if not np.isfinite(xyz).all():
            raise ProxycodecError("points3D holds non-finite coordinates", path)
        return ids, xyz, rgb, err, offsets, img_ids, p2d
    finally:
        r.close()


# ---------------------------------------------------------------------------------------- text reading
def _text_lines(path: Path) -> list[str]:
    try:
        size = path.stat().st_size
        if size > _MAX_TEXT_BYTES:
            raise ProxycodecError(f"text model file is {size} bytes; use the binary format", path)
        with open(path, encoding="utf-8") as fh:
            return fh.read().splitlines()
    except FileNotFoundError:
        raise ProxycodecError("file not found", path) from None
    except UnicodeDecodeError:
        raise ProxycodecError("file is not UTF-8 text", path) from None


def _is_data(line: str) -> bool:
    s = line.strip()
    return bool(s) and not s.startswith("#")


def read_cameras_txt(path: str | os.PathLike) -> dict[int, ColmapCamera]:
    path = Path(path)
    cams: dict[int, ColmapCamera] = {}
    for lineno, line in enumerate(_text_lines(path), start=1):
        if not _is_data(line):
            continue
        w = line.split()
        try:
            cid, model, width, height = int(w[0]), w[1], int(w[2]), int(w[3])
            params = np.array([float(v) for v in w[4:]])
        except (IndexError, ValueError):
            raise ProxycodecError(f"line {lineno}: malformed camera line", path) from None
        if model not in _MODEL_BY_NAME:
            raise ProxycodecError(f"line {lineno}: unknown camera model {model!r}", path)
        if params.shape[0] != _MODEL_BY_NAME[model][1]:
            raise ProxycodecError(
                f"line {lineno}: camera model {model} needs {_MODEL_BY_NAME[model][1]} "
                f"parameters, got {params.shape[0]}",
                path,
            )
        cams[cid] = _make_camera(path, cid, model, width, height, params)
    return cams


def read_images_txt(path: str | os.PathLike, *, keypoints: bool = False) -> list[ColmapImage]:
    """Two lines per image: ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then ``X Y POINT3D_ID ...``."""
    path = Path(path)
    lines = _text_lines(path)
    images: list[ColmapImage] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        i += 1
        if not _is_data(line):
            continue
        w = line.strip().split(maxsplit=9)
        try:
            iid = int(w[0])
            q = np.array([float(v) for v in w[1:5]])
            t = np.array([float(v) for v in w[5:8]])
            cid = int(w[8])
            name = w[9]
        except (IndexError, ValueError):
            raise ProxycodecError(f"line {i}: malformed image line", path) from None
        if i >= len(lines):
            raise ProxycodecError(f"image {iid} ({name!r}) has no keypoint line", path)
        kp_line = lines[i]
        i += 1
        n_tok = len(kp_line.split())
        if n_tok % 3:
            raise ProxycodecError(
                f"line {i}: keypoint line of image {iid} does not hold (X, Y, POINT3D_ID) triples", path
            )
        xys = ids = None
        if keypoints and n_tok:
            try:
                kp = np.array(kp_line.split(), dtype=np.float64).reshape(-1, 3)
            except ValueError:
                raise ProxycodecError(f"line {i}: malformed keypoint line", path) from None
            pid = kp[:, 2]
            if not (np.isfinite(kp).all() and np.all(pid == np.round(pid)) and np.all(np.abs(pid) < 2.0**63)):
                raise ProxycodecError(f"line {i}: keypoints must be finite with integer POINT3D_IDs", path)
            xys, ids = kp[:, :2].copy(), pid.astype(np.int64)
        elif keypoints:
            xys, ids = np.zeros((0, 2)), np.zeros(0, np.int64)
        if not _valid_pose(q, t):
            raise ProxycodecError(f"image {iid} ({name!r}) has an invalid pose", path)
        images.append(ColmapImage(iid, q, t, cid, name, n_tok // 3, xys, ids))
    return images


def read_points3d_txt(path: str | os.PathLike) -> tuple[np.ndarray, ...]:
    """As :func:`read_points3d_bin`, from lines ``POINT3D_ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)*``."""
    path = Path(path)
    ids, xyz, rgb, err, lengths = [], [], [], [], []
    track: list[str] = []
    for lineno, line in enumerate(_text_lines(path), start=1):
        if not _is_data(line):
            continue
        w = line.split()
        if len(w) < 8 or (len(w) - 8) % 2:
            raise ProxycodecError(f"line {lineno}: malformed point line", path)
        try:
            ids.append(int(w[0]))
            xyz.append((float(w[1]), float(w[2]), float(w[3])))
            rgb.append((int(w[4]), int(w[5]), int(w[6])))
            err.append(float(w[7]))
        except ValueError:
            raise ProxycodecError(f"line {lineno}: malformed point line", path) from None
        lengths.append((len(w) - 8) // 2)
        track.extend(w[8:])
    try:
        tr = np.array(track, dtype=np.int64).reshape(-1, 2)
        rgb_a = np.array(rgb, dtype=np.int64).reshape(-1, 3)
        ids_a = np.asarray(ids, dtype=np.int64)
    except (ValueError, OverflowError):  # OverflowError: an integer beyond int64
        raise ProxycodecError("malformed point id, track or colour values", path) from None
    if tr.size and (tr.min() < np.iinfo(np.int32).min or tr.max() > np.iinfo(np.int32).max):
        raise ProxycodecError("track image ids / keypoint indices do not fit in 32 bits", path)
    if rgb_a.size and (rgb_a.min() < 0 or rgb_a.max() > 255):
        raise ProxycodecError("point colours must be in 0..255", path)
    xyz_a = np.array(xyz, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(xyz_a).all():
        raise ProxycodecError("points3D holds non-finite coordinates", path)
    offsets = np.zeros(len(lengths) + 1, np.int64)
    np.cumsum(np.asarray(lengths, dtype=np.int64), out=offsets[1:])
    return (
        ids_a,
        xyz_a,
        rgb_a.astype(np.uint8),
        np.asarray(err, dtype=np.float64),
        offsets,
        tr[:, 0].astype(np.int32),
        tr[:, 1].astype(np.int32),
    )


# ------------------------------------------------------------------------------------------------ model
def find_sparse_dir(root: str | os.PathLike) -> Path:
    """``root/sparse/0``, ``root/sparse`` or ``root`` itself: the first that holds a COLMAP model."""
    root = Path(root)
    for d in (root / "sparse" / "0", root / "sparse", root):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    raise ProxycodecError("no COLMAP model found (looked for sparse/0/cameras.bin or .txt)", root)


def read_colmap_model(sparse_dir: str | os.PathLike, *, keypoints: bool = False) -> ColmapModel:
    """Read ``cameras``, ``images`` and ``points3D`` from a model folder (``.bin`` preferred to ``.txt``)."""
    d = Path(sparse_dir)

    def pick(stem: str) -> tuple[Path, bool]:
        if (d / f"{stem}.bin").is_file():
            return d / f"{stem}.bin", True
        if (d / f"{stem}.txt").is_file():
            return d / f"{stem}.txt", False
        raise ProxycodecError(f"COLMAP model lacks {stem}.bin / {stem}.txt", d)

    p, binary = pick("cameras")
    cams = read_cameras_bin(p) if binary else read_cameras_txt(p)
    p, binary = pick("images")
    imgs = read_images_bin(p, keypoints=keypoints) if binary else read_images_txt(p, keypoints=keypoints)
    for im in imgs:
        if im.camera_id not in cams:
            raise ProxycodecError(f"image {im.id} ({im.name!r}) refers to missing camera {im.camera_id}", p)
    if len({im.id for im in imgs}) != len(imgs):
        raise ProxycodecError("image ids repeat", p)
    if (d / "points3D.bin").is_file():
        pts = read_points3d_bin(d / "points3D.bin")
    elif (d / "points3D.txt").is_file():
        pts = read_points3d_txt(d / "points3D.txt")
    else:
        pts = (
            np.zeros(0, np.int64),
            np.zeros((0, 3)),
            np.zeros((0, 3), np.uint8),
            np.zeros(0),
            np.zeros(1, np.int64),
            np.zeros(0, np.int32),
            np.zeros(0, np.int32),
        )
    return ColmapModel(cams, imgs, *pts)


def pinhole_intrinsics(
    cam: ColmapCamera, path: str | os.PathLike | None = None
) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a pinhole camera; radial models qualify only with all distortion exactly zero."""
    if cam.model not in _PINHOLE_LIKE:
        raise ProxycodecError(
            f"camera {cam.id} uses the {cam.model} model (fisheye); proxycodec needs undistorted "
            "pinhole images and undistorts only the SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV models itself: "
            "undistort them first (e.g. `colmap image_undistorter`)",
            path,
        )
    ifx, ify, icx, icy = _PINHOLE_LIKE[cam.model]
    n_intr = len({ifx, ify, icx, icy})
    dist = cam.params[n_intr:]
    if np.any(dist != 0):
        coeffs = ", ".join(f"{v:.6g}" for v in dist)
        hint = (
            " (or load with undistortion on: the default, turned off by --no-undistort / undistort=False)"
            if cam.model in UNDISTORTABLE_MODELS
            else ""
        )
        raise ProxycodecError(
            f"camera {cam.id} uses the {cam.model} model with non-zero distortion ({coeffs}); "
            "proxycodec needs undistorted pinhole images: undistort them first "
            f"(e.g. `colmap image_undistorter`){hint}",
            path,
        )
    p = cam.params
    return float(p[ifx]), float(p[ify]), float(p[icx]), float(p[icy])


def load_colmap(
    root: str | os.PathLike,
    *,
    images: str = "images",
    max_width: int | None = None,
    test_every: int = 8,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    cache_bytes: int = DEFAULT_CACHE_BYTES,
    undistort: bool = True,
) -> PosedImages:
    """Load a COLMAP scene folder (``<root>/sparse/0`` + ``<root>/<images>/``).

    * Cameras are sorted by image name; test = every ``test_every``-th image in that order (index % test_every
      == 0, the Mip-NeRF 360 convention), the rest train; ``test_every=0`` means no test split.
    * Pinhole cameras are used as they are (radial models with all-zero distortion count as pinhole). With
      ``undistort`` (the default) cameras of the SIMPLE_RADIAL, RADIAL, OPENCV and FULL_OPENCV models with
      non-zero distortion become the pinhole camera of :meth:`DistortedCamera.pinhole` (same size and principal
      point, focal scaled so that no output pixel is blank, as ``colmap image_undistorter``), and their images
      are undistorted lazily, at full resolution, when loaded (:mod:`.undistort`). Other models (fisheye, FOV),
      and any distortion when ``undistort`` is False, raise :class:`ProxycodecError` saying to undistort first.
    * ``images`` may name a downscaled folder (``images_4``): intrinsics are scaled per axis by the ratio of
      the actual image size to the COLMAP camera size (which must agree in aspect ratio to within a pixel).
    * ``max_width`` then applies 3DGS's rule (:meth:`Camera.with_max_width`) to get the 100% reference
      resolution.
    * ``points``/``point_colors``: the SfM points (float32 / uint8). ``bounds``: per axis, the 0.5th..99.5th
      percentile of the points (SfM leaves a few far-away outliers), or :func:`look_at_bounds` of the cameras
      when the model has fewer than 8 points.
    """
    root = Path(root)
    if not root.is_dir():
        raise ProxycodecError("COLMAP dataset folder not found", root)
    if isinstance(test_every, bool) or int(test_every) < 0:
        raise ProxycodecError(f"test_every must be >= 0, got {test_every!r}")
    if max_width is not None and (isinstance(max_width, bool) or int(max_width) < 1):
        raise ProxycodecError(f"max_width must be a positive integer, got {max_width!r}")
    sparse = find_sparse_dir(root)
    model = read_colmap_model(sparse)
    cam_file = sparse / ("cameras.bin" if (sparse / "cameras.bin").is_file() else "cameras.txt")
    img_dir = root / images
    if not img_dir.is_dir():
        raise ProxycodecError(f"image folder {images!r} not found", root)
    if not model.images:
        raise ProxycodecError("COLMAP model has no registered images", sparse)
    intr: dict[int, tuple[float, float, float, float] | None] = {}  # None: undistorted per image size
    for cid in sorted({im.camera_id for im in model.images}):
        cc = model.cameras[cid]
        if undistort and _needs_undistortion(cc):
            intr[cid] = None
        else:
            intr[cid] = pinhole_intrinsics(cc, cam_file)
    remap_cache = RemapCache()
    undistorters: dict[DistortedCamera, Undistorter] = {}
    per_image: list[Undistorter | None] = []
    cams: list[Camera] = []
    sizes: list[tuple[int, int]] = []
    for im in sorted(model.images, key=lambda m: m.name):
        cc = model.cameras[im.camera_id]
        path = img_dir / im.name
        w, h = image_file_size(path)
        if (w, h) != (cc.width, cc.height):
            sx, sy = w / cc.width, h / cc.height
            if abs(h - cc.height * sx) > 1.0 or abs(w - cc.width * sy) > 1.0:
                raise ProxycodecError(
                    f"image is {w}x{h} but its COLMAP camera {cc.id} is {cc.width}x{cc.height} "
                    "(not a uniformly scaled copy)",
                    path,
                )
        else:
            sx = sy = 1.0
        pin = intr[im.camera_id]
        if pin is None:
            try:
                dc = DistortedCamera.from_colmap(cc.model, cc.params, cc.width, cc.height, (w, h))
                und = undistorters.get(dc)
                if und is None:
                    und = undistorters[dc] = Undistorter(dc, remap_cache)
                fx, fy, cx, cy = und.camera.pinhole()  # the shared camera: its scale is computed once
            except ProxycodecError as e:
                raise ProxycodecError(f"camera {cc.id}: {e.reason}", cam_file) from None
            per_image.append(und)
        else:
            fx, fy, cx, cy = pin
            fx, fy, cx, cy = fx * sx, fy * sy, cx * sx, cy * sy
            per_image.append(None)
        cam = Camera(im.world_to_camera, fx, fy, cx, cy, w, h, name=im.name, image_path=str(path))
        if max_width is not None:
            cam = cam.with_max_width(int(max_width))
        cams.append(cam)
        sizes.append((w, h))
    n = len(cams)
    if test_every:
        test = [i for i in range(n) if i % int(test_every) == 0]
        train = [i for i in range(n) if i % int(test_every) != 0]
    else:
        test, train = [], list(range(n))
    if model.points.shape[0] >= 8:
        lo, hi = np.percentile(model.points, [0.5, 99.5], axis=0)
        bounds = np.stack([lo, hi])
    else:
        bounds = look_at_bounds(cams)
    return PosedImages(
        cameras=cams,
        train_indices=train,
        test_indices=test,
        points=model.points.astype(np.float32),
        point_colors=model.colors,
        bounds=bounds,
        background=tuple(float(v) for v in background),  # type: ignore[arg-type]
        file_sizes=sizes,
        root=str(root),
        kind="colmap",
        cache_bytes=cache_bytes,
        undistorters=per_image if any(u is not None for u in per_image) else None,
    )


def _needs_undistortion(cam: ColmapCamera) -> bool:
    """A radial (non-fisheye) camera with some non-zero distortion coefficient."""
    if cam.model not in UNDISTORTABLE_MODELS:
        return False
    ifx, ify, icx, icy = _PINHOLE_LIKE[cam.model]
    return bool(np.any(cam.params[len({ifx, ify, icx, icy}) :] != 0))
