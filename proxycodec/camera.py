"""Pinhole camera whose intrinsics scale with the resolution ratio xi.

Convention (the one COLMAP, OpenCV and gsplat use): camera axes x right, y down, z forward; pixel (i, j)
covers [i, i+1) x [j, j+1), so its centre is (i + 0.5, j + 0.5) and a principal point at the image centre is
(W/2, H/2). ``world_to_camera`` maps world points to camera coordinates: p_cam = R @ p_world + t.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from .devices import upload
from .errors import ProxycodecError

if TYPE_CHECKING:
    import torch

#: The range of resolution ratios every renderer accepts (issue: "xi in [0.025, 2.0] at least").
XI_MIN = 0.025
XI_MAX = 2.0


def check_xi(xi: float) -> float:
    xi = float(xi)
    if not math.isfinite(xi) or not (XI_MIN <= xi <= XI_MAX):
        raise ProxycodecError(f"resolution ratio {xi!r} is outside [{XI_MIN}, {XI_MAX}]")
    return xi


def _as_matrix(m) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ProxycodecError(f"camera pose must be a finite 4x4 matrix, got shape {m.shape}")
    return m


@dataclass(frozen=True, eq=False)
class Camera:
    """A posed pinhole camera at its 100% reference resolution (``width`` x ``height`` pixels)."""

    world_to_camera: np.ndarray  # [4, 4] float64
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    name: str = ""
    image_path: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "world_to_camera", _as_matrix(self.world_to_camera))
        for k in ("fx", "fy", "cx", "cy"):
            v = float(getattr(self, k))
            if not math.isfinite(v):
                raise ProxycodecError(f"camera {self.name!r}: {k} is not finite")
            object.__setattr__(self, k, v)
        if self.fx <= 0 or self.fy <= 0:
            raise ProxycodecError(f"camera {self.name!r}: focal lengths must be positive")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ProxycodecError(f"camera {self.name!r}: image size {self.width}x{self.height} is empty")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (np.array_equal(self.world_to_camera, other.world_to_camera) and self.name == other.name
                and (self.fx, self.fy, self.cx, self.cy, self.width, self.height)
                == (other.fx, other.fy, other.cx, other.cy, other.width, other.height))

    __hash__ = None  # type: ignore[assignment]

    # ------------------------------------------------------------------ geometry
    @property
    def rotation(self) -> np.ndarray:  # [3, 3] world -> camera
        return self.world_to_camera[:3, :3]

    @property
    def translation(self) -> np.ndarray:  # [3]
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> np.ndarray:
        """Camera position in world coordinates."""
        return -self.rotation.T @ self.translation

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    def scaled(self, xi: float) -> "Camera":
        """The same camera rendering ``round(xi*W) x round(xi*H)`` pixels (at least 1x1).

        Intrinsics scale by the realised size ratio per axis, so the image covers exactly the same field of view.
        """
        xi = check_xi(xi)
        return self.sized(max(1, int(round(xi * self.width))), max(1, int(round(xi * self.height))))

    def sized(self, width: int, height: int) -> "Camera":
        """The same camera rendering exactly ``width x height`` pixels (intrinsics scaled per axis, so the image
        covers the same field of view): ``scaled`` with the size given instead of the ratio."""
        w, h = int(width), int(height)
        if w < 1 or h < 1:
            raise ProxycodecError(f"image size must be at least 1 x 1, got {w} x {h}")
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w, height=h)

    def with_max_width(self, max_width: int) -> "Camera":
        """3DGS's resolution rule: an image wider than ``max_width`` is downscaled to that width."""
        if self.width <= max_width:
            return self
        s = max_width / self.width
        w = int(max_width)
        h = max(1, int(round(self.height * s)))
        sx, sy = w / self.width, h / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=w, height=h)

    def torch_params(self, device=None, dtype=None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(R [3,3], t [3], center [3]) as tensors (float32 unless ``dtype`` says otherwise)."""
        import torch  # here, not at the top: cameras are also used by the torch-free decode path

        if dtype is None:
            dtype = torch.float32
        R = upload(self.rotation, device, dtype)
        t = upload(self.translation, device, dtype)
        c = upload(self.center, device, dtype)
        return R, t, c

    # ------------------------------------------------------------------ construction helpers
    @staticmethod
    def look_at(eye, target, up=(0.0, 0.0, 1.0), *, fov_x_deg: float = 50.0, width: int = 200, height: int = 200,
                name: str = "") -> "Camera":
        """A camera at ``eye`` looking at ``target`` (OpenCV axes: image y points away from ``up``)."""
        eye = np.asarray(eye, dtype=np.float64)
        target = np.asarray(target, dtype=np.float64)
        up = np.asarray(up, dtype=np.float64)
        z = target - eye
        z /= np.linalg.norm(z)
        x = np.cross(z, up)
        if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
            x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])  # rows: camera axes in world
        m = np.eye(4)
        m[:3, :3] = R
        m[:3, 3] = -R @ eye
        fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
        return Camera(m, fx, fx, width / 2, height / 2, width, height, name=name)

    @staticmethod
    def from_opengl_c2w(c2w, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                        name: str = "", image_path: str | None = None) -> "Camera":
        """From a camera-to-world matrix in the OpenGL/Blender convention (y up, z backward)."""
        c2w = np.asarray(c2w, dtype=np.float64).copy()
        if c2w.shape != (4, 4):
            raise ProxycodecError(f"camera {name!r}: transform_matrix must be 4x4, got {c2w.shape}")
        c2w[:3, 1:3] *= -1.0  # OpenGL -> OpenCV axes
        try:
            w2c = np.linalg.inv(c2w)
        except np.linalg.LinAlgError as e:
            raise ProxycodecError(f"camera {name!r}: transform_matrix is singular") from e
        return Camera(w2c, fx, fy, cx, cy, width, height, name=name, image_path=image_path)

    def to_json(self) -> dict:
        return {"name": self.name, "width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "world_to_camera": self.world_to_camera.tolist()}

    @staticmethod
    def from_json(d: dict) -> "Camera":
        try:
            return Camera(np.asarray(d["world_to_camera"], dtype=np.float64), d["fx"], d["fy"], d["cx"], d["cy"],
                          int(d["width"]), int(d["height"]), name=str(d.get("name", "")))
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, ProxycodecError):
                raise
            raise ProxycodecError(f"bad camera record: {e}") from e


def orbit_cameras(center, radius: float, n: int, *, elevation_deg: float = 25.0, fov_x_deg: float = 45.0,
                  width: int = 256, height: int = 256, up=(0.0, 0.0, 1.0)) -> list[Camera]:
    """``n`` cameras on a circle around ``center`` looking at it (z up)."""
    center = np.asarray(center, dtype=np.float64)
    el = math.radians(elevation_deg)
    cams = []
    for i in range(n):
        az = 2 * math.pi * i / n
        eye = center + radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        cams.append(Camera.look_at(eye, center, up, fov_x_deg=fov_x_deg, width=width, height=height,
                                   name=f"orbit_{i:03d}"))
    return cams


def default_cameras(cameras, bounds, n: int = 8, width: int = 256, height: int = 192) -> list[Camera]:
    """``cameras`` when there are any, else ``n`` orbit cameras around the box ``bounds`` ([2, 3]: min, max).

    What ``proxycodec decode`` renders when no cameras are given (``codec.default_cameras``, ``proxycodec.lite``).
    """
    if cameras:
        return list(cameras)
    b = np.asarray(bounds, dtype=np.float64)
    c = b.mean(0)
    r = max(float(np.linalg.norm(b[1] - b[0])) / 2.0, 1e-3)
    return orbit_cameras(c, 2.2 * r, n, elevation_deg=30.0, fov_x_deg=50.0, width=width, height=height)
