"""The anchor scene: what the codec compresses (METHOD.md section 1, Scaffold-GS).

A frozen dataclass of tensors with ``validate()``; trainable state lives elsewhere (``proxycodec.train``) and
exports an ``AnchorScene``. Scalings are stored in log space exactly as Scaffold-GS stores them: the first three
scale the offsets, the last three are the base scale of the anchor's Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch

from .errors import ProxycodecError


@dataclass(frozen=True)
class AnchorScene:
    positions: torch.Tensor  # [M, 3] float32, anchor centres (on the voxel grid)
    features: torch.Tensor  # [M, F] float32
    offsets: torch.Tensor  # [M, K, 3] float32, in units of exp(scalings[:, :3])
    scalings: torch.Tensor  # [M, 6] float32, log space
    voxel_size: float
    metadata: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def num_anchors(self) -> int:
        return int(self.positions.shape[0])

    @property
    def feat_dim(self) -> int:
        return int(self.features.shape[1])

    @property
    def n_offsets(self) -> int:
        return int(self.offsets.shape[1])

    def validate(self, source: str | None = None) -> "AnchorScene":
        """Check shapes, dtypes and finiteness; raise ``ProxycodecError`` naming the first problem."""
        M = self.positions.shape[0] if self.positions.ndim == 2 else -1
        checks = [
            ("positions", self.positions, (M, 3)),
            ("features", self.features, (M, self.features.shape[-1] if self.features.ndim == 2 else -1)),
            ("offsets", self.offsets, (M, self.offsets.shape[1] if self.offsets.ndim == 3 else -1, 3)),
            ("scalings", self.scalings, (M, 6)),
        ]
        for name, t, shape in checks:
            if not isinstance(t, torch.Tensor):
                raise ProxycodecError(f"anchor {name} must be a tensor", source)
            if tuple(t.shape) != shape or M < 0:
                raise ProxycodecError(f"anchor {name} has shape {tuple(t.shape)}, expected {shape}", source)
            if not t.dtype.is_floating_point:
                raise ProxycodecError(f"anchor {name} must be floating point, got {t.dtype}", source)
            if M and not bool(torch.isfinite(t).all()):
                raise ProxycodecError(f"anchor {name} contains NaN or Inf", source)
        if not (isinstance(self.voxel_size, (int, float)) and math.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise ProxycodecError(f"voxel size must be a positive finite number, got {self.voxel_size!r}", source)
        return self

    def to(self, device=None, dtype=None) -> "AnchorScene":
        f = lambda t: t.to(device=device, dtype=dtype)  # noqa: E731
        return replace(self, positions=f(self.positions), features=f(self.features), offsets=f(self.offsets),
                       scalings=f(self.scalings))

    def subset(self, index: torch.Tensor) -> "AnchorScene":
        return replace(self, positions=self.positions[index], features=self.features[index],
                       offsets=self.offsets[index], scalings=self.scalings[index])

    def bounds(self) -> np.ndarray:
        """[2, 3] axis-aligned bounds of the anchor positions (zeros for an empty scene)."""
        if self.num_anchors == 0:
            return np.zeros((2, 3))
        p = self.positions.detach().cpu().double().numpy()
        return np.stack([p.min(0), p.max(0)])

    def extent_radius(self) -> torch.Tensor:
        """[M] radius of a sphere around each anchor containing every Gaussian's 3-sigma ellipsoid.

        Neural scales are exp(l[3:6]) * sigmoid(.) <= exp(l[3:6]), so this bound holds for any MLP output.
        """
        off = (self.offsets * torch.exp(self.scalings[:, None, :3])).norm(dim=-1).amax(dim=1) if self.n_offsets else 0
        return off + 3.0 * torch.exp(self.scalings[:, 3:]).amax(dim=1)


def scene_from_scaffold_ply(ply, voxel_size: float | None = None, source: str | None = None) -> AnchorScene:
    """Build an ``AnchorScene`` from a ``formats.scaffold_ply.ScaffoldPly``.

    Scaffold-GS does not store the voxel size in the PLY; when not given, it is estimated as the anchors' median
    nearest-neighbour distance (``estimate_voxel_size``), the grid step of a voxelised set.
    """
    pos = torch.from_numpy(np.array(ply.positions, dtype=np.float32, copy=True))
    scene = AnchorScene(
        positions=pos,
        features=torch.from_numpy(np.array(ply.features, dtype=np.float32, copy=True)),
        offsets=torch.from_numpy(np.array(ply.offsets, dtype=np.float32, copy=True)),
        scalings=torch.from_numpy(np.array(ply.scalings, dtype=np.float32, copy=True)),
        voxel_size=float(voxel_size) if voxel_size else estimate_voxel_size(pos),
    )
    return scene.validate(source)


def point_spacing(points: np.ndarray) -> float:
    """The median distance from each point to its nearest other distinct point (Scaffold-GS's automatic voxel size);
    0 when fewer than two distinct points. A k-d tree over every point: O(N log N) time, O(N) memory."""
    from scipy.spatial import cKDTree

    pts = np.unique(np.asarray(points, dtype=np.float64), axis=0)
    if len(pts) < 2:
        return 0.0
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(np.median(d[:, 1]))


def estimate_voxel_size(positions: torch.Tensor) -> float:
    """The grid step of voxelised anchors: their ``point_spacing`` (1.0 when there is no spacing to measure)."""
    spacing = point_spacing(positions.detach().cpu().numpy())
    return spacing if spacing > 0 else 1.0
