"""An anchor scene decoded for one resolution as plain 3DGS Gaussians: what ``decode --ply/--spz/--glb/--lod`` write.

A neural Gaussian's opacity, scale, rotation and colour are MLP outputs of the view (direction, distance) and its
opacity is gated by its pixel footprint at the rendered resolution (SPEC section 2). A standard 3DGS file holds one
value per Gaussian, colour as spherical harmonics (SH) of the view direction, and no gate. ``bake`` decodes the scene
from a set of views at resolution ``xi`` (the stored cameras plus a Fibonacci sphere of look-at views at the cameras'
median distance) and keeps, per neural Gaussian (anchor, slot):

- **opacity**: the mean over the views that see it of the *gated* opacity ``o * g`` (0 where the opacity MLP drops
  it). Gaussians below 1/255 are left out: what the gate switches off at ``xi`` is not in the file, so a file for a
  lower resolution holds fewer Gaussians (a level of detail).
- **scale / rotation**: the weighted mean (weight ``o * g``) of the log scales and of the sign-aligned quaternions.
- **colour**: a weighted least-squares fit of real SH of ``sh_degree`` 0..3 (3DGS's basis and ``+ 0.5`` offset) to
  the colours it showed from each view's direction, with a small ridge on the degree >= 1 terms; or
  (``view=i``) the colours of stored camera ``i`` baked into the DC term, where that camera sees the Gaussian.
- **position**: exact (the anchor position plus its scaled offset does not depend on the view).

Rendering at ``xi`` from a distance ``D`` puts as many pixels on a Gaussian as rendering at 100% from ``D / xi``, so
a file baked for ``xi`` serves a full-resolution viewer from ``1 / xi`` times the cameras' distance: the LOD set's
``distance_scale``.

Cost: one decode + projection per view, O(views x anchors x K); memory O(anchors x K x (degree + 1)^4) floats for
the normal equations. Deterministic (index_add on the CPU, fixed views).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from .camera import Camera, check_xi
from .errors import ProxycodecError
from .formats.inria_ply import SH_C0, GaussianPly

#: Opacity below which a baked Gaussian is left out (the compositor's skip threshold).
MIN_OPACITY = 1.0 / 255.0
#: Export formats by file suffix.
FORMATS = ("ply", "spz", "glb")
#: Default LOD levels (resolution ratios), finest first.
DEFAULT_LEVELS = (1.0, 0.5, 0.25, 0.125)
LOD_MANIFEST = "lod.json"


@dataclass(frozen=True)
class BakeConfig:
    """How ``bake`` turns the view-dependent neural Gaussians into one plain 3DGS set."""

    xi: float = 1.0  # resolution ratio the set is decoded for
    sh_degree: int = 1  # colour as SH of this degree (0..3), fitted over the views
    view: int | None = None  # bake stored camera ``view``'s colours instead (SH degree 0)
    directions: int | None = None  # look-at views beside the stored cameras (None: 0 with >= 8 stored, else 32)
    ridge: float = 0.05  # ridge on the degree >= 1 SH terms, relative to each Gaussian's total weight
    min_opacity: float = MIN_OPACITY

    def __post_init__(self) -> None:
        check_xi(self.xi)
        if not 0 <= int(self.sh_degree) <= 3:
            raise ProxycodecError(f"SH degree must be 0..3, got {self.sh_degree}")
        if self.directions is not None and self.directions < 0:
            raise ProxycodecError(f"directions must be >= 0, got {self.directions}")


@dataclass
class Baked:
    """The Gaussians of one bake and what it did."""

    ply: GaussianPly
    info: dict


# ================================================================================================ views
def scene_frame(model) -> tuple[np.ndarray, float, np.ndarray, Camera]:
    """(centre, radius, up, template camera) of the views around a scene: the anchors' box centre, the stored
    cameras' median distance to it (else twice the box diagonal), their mean up vector (else +z) and the first
    stored camera (else a 256 x 192 camera of 50 degrees)."""
    pos = model.scene.positions.detach().double().cpu().numpy()
    lo, hi = (pos.min(0), pos.max(0)) if len(pos) else (np.zeros(3), np.zeros(3))
    center = 0.5 * (lo + hi)
    cams = list(model.cameras or [])
    if cams:
        radius = float(np.median([np.linalg.norm(c.center - center) for c in cams]))
        up = -np.mean([c.rotation[1] for c in cams], axis=0)
        template = cams[0]
    else:
        radius = 2.0 * float(np.linalg.norm(hi - lo))
        up = np.array([0.0, 0.0, 1.0])
        template = Camera.look_at(center + np.array([radius, 0, 0]), center, up, fov_x_deg=50.0, width=256,
                                  height=192)
    n = np.linalg.norm(up)
    up = up / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])
    return center, max(radius, 1e-6), up, template


def _spiral(n: int, offset: float) -> np.ndarray:
    """[n, 3] unit vectors on a Fibonacci spiral, pole +z (``offset`` 0.5: the usual lattice)."""
    i = np.arange(n) + offset
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    phi = math.pi * (1.0 + 5.0 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def sphere_cameras(model, n: int, *, offset: float = 0.5, name: str = "sphere") -> list[Camera]:
    """Up to ``n`` look-at cameras around the scene (``scene_frame``), with the template camera's field of view and
    size, at directions within the stored cameras' coverage: a Fibonacci spiral (``offset`` shifts it) of which only
    directions at most the cameras' widest gap (the largest angle from a camera to its nearest neighbour) from some
    stored camera are kept, so views stay where the scene was captured from (lego: the upper hemisphere; a 360°
    capture: its ring). Without stored cameras: the whole sphere."""
    if n <= 0:
        return []
    center, radius, up, t = scene_frame(model)
    fov_x = math.degrees(2.0 * math.atan(0.5 * t.width / t.fx))
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    cams = list(model.cameras or [])
    if len(cams) >= 2:
        cd = np.array([c.center - center for c in cams], dtype=np.float64)
        cd /= np.linalg.norm(cd, axis=1, keepdims=True).clip(1e-12)
        cos = np.clip(cd @ cd.T, -1.0, 1.0)
        np.fill_diagonal(cos, -1.0)
        gap = float(np.arccos(cos.max(1)).max())
        dirs = None
        for m in (n, 2 * n, 4 * n, 8 * n, 16 * n):  # denser spirals until n directions fall inside the coverage
            sp = _spiral(m, offset)
            d = sp[:, :1] * e1 + sp[:, 1:2] * e2 + sp[:, 2:] * up
            inside = np.arccos(np.clip(d @ cd.T, -1.0, 1.0)).min(1) <= gap
            dirs = d[inside]
            if len(dirs) >= n:
                break
        dirs = dirs[np.linspace(0, len(dirs) - 1, min(n, len(dirs))).round().astype(int)] if len(dirs) else dirs
    else:
        sp = _spiral(n, offset)
        dirs = sp[:, :1] * e1 + sp[:, 1:2] * e2 + sp[:, 2:] * up
    return [Camera.look_at(center + radius * d, center, up, fov_x_deg=fov_x, width=t.width, height=t.height,
                           name=f"{name}_{i:03d}") for i, d in enumerate(dirs)]


#: Stored cameras from which a bake adds no sphere views, and the sphere views it adds below that.
ENOUGH_CAMERAS, FEW_CAMERAS_DIRECTIONS = 8, 32


def bake_cameras(model, directions: int | None = None) -> list[Camera]:
    """The views a bake decodes: the stored cameras, then ``directions`` sphere views (None: none when at least
    ``ENOUGH_CAMERAS`` are stored, else ``FEW_CAMERAS_DIRECTIONS``). Why: on lego's container (16 stored cameras)
    held-out PSNR is 35.58 / 35.05 / 34.67 dB with 0 / 16 / 64 sphere views added (SPEC section 13)."""
    stored = list(model.cameras or [])
    if directions is None:
        directions = 0 if len(stored) >= ENOUGH_CAMERAS else FEW_CAMERAS_DIRECTIONS
    return stored + sphere_cameras(model, directions)


def held_out_cameras(model, n: int = 8) -> list[Camera]:
    """Sphere views between the bake's (another spiral offset): directions no bake was fitted on."""
    return sphere_cameras(model, n, offset=0.17, name="held_out")


# ================================================================================================ bake
def _sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """[N, (degree+1)^2] real SH basis of 3DGS's ``eval_sh`` at unit ``dirs`` [N, 3]."""
    from .explicit import eval_sh

    nc = (degree + 1) ** 2
    eye = torch.eye(nc, dtype=dirs.dtype).expand(dirs.shape[0], nc, nc)
    return eval_sh(degree, eye, dirs)


def bake(model, cfg: BakeConfig = BakeConfig(), *, cameras: list[Camera] | None = None) -> Baked:
    """Decode ``model`` (a ``SceneModel``) at ``cfg.xi`` from ``cameras`` (default ``bake_cameras``) into one set of
    plain 3DGS Gaussians (module docstring)."""
    from .model import decode_view
    from .render.project import project_gaussians

    s = model.scene
    dec = model.decoder
    M, K = s.num_anchors, s.n_offsets
    S = M * K
    degree = 0 if cfg.view is not None else int(cfg.sh_degree)
    nc = (degree + 1) ** 2
    views = list(cameras) if cameras is not None else bake_cameras(model, cfg.directions)
    if cfg.view is not None and not 0 <= cfg.view < len(model.cameras or []):
        raise ProxycodecError(f"view {cfg.view} does not exist ({len(model.cameras or [])} stored cameras)")
    if not views:
        raise ProxycodecError("no views to decode the scene from")
    dev = s.positions.device  # baked where the scene lies
    f64 = dict(dtype=torch.float64, device=dev)
    seen = torch.zeros(S, **f64)
    w_sum = torch.zeros(S, **f64)
    ls_sum = torch.zeros(S, 3, **f64)
    q_sum = torch.zeros(S, 4, **f64)
    q_ref = torch.zeros(S, 4, **f64)
    has_ref = torch.zeros(S, dtype=torch.bool, device=dev)
    A = torch.zeros(S, nc, nc, **f64)
    b = torch.zeros(S, nc, 3, **f64)
    baked_dc = torch.full((S, 3), float("nan"), **f64)
    # Centres do not depend on the view: x_v + O_k exp(l[0:3]), in float64.
    all_means = (s.positions.detach().double()[:, None, :] + s.offsets.detach().double()
                 * torch.exp(s.scalings.detach().double()[:, None, :3])).reshape(S, 3)
    view_cam = model.cameras[cfg.view] if cfg.view is not None else None
    if view_cam is not None and view_cam not in views:
        views = views + [view_cam]
    with torch.no_grad():
        for cam in views:
            cx = cam.scaled(cfg.xi)
            g, vis = decode_view(s, dec, cx, cfg.xi)
            slots_all = (vis[:, None] * K + torch.arange(K, device=dev)).reshape(-1)
            seen.index_add_(0, slots_all, torch.ones(slots_all.shape[0], **f64))
            if g.count == 0:
                continue
            slot = g.anchor_index * K + g.slot
            proj = project_gaussians(g.means, g.quats, g.scales, torch.ones_like(g.opacities), g.colors, cx,
                                     gate=dec.config.gate, near=dec.config.near_plane(), origin=g.origin)
            shown = torch.zeros(g.count, dtype=torch.bool, device=dev)
            shown[proj.index] = True
            # Decoded but outside the image: not seen from this view after all.
            seen.index_add_(0, slot[~shown], -torch.ones(int((~shown).sum()), **f64))
            i = proj.index
            si = slot[i]
            w = (g.opacities[i] * proj.gate).double()
            w_sum.index_add_(0, si, w)
            ls_sum.index_add_(0, si, w[:, None] * torch.log(g.scales[i].double().clamp_min(1e-30)))
            q = g.quats[i].double()
            q = q / q.norm(dim=1, keepdim=True).clamp_min(1e-12)
            new = ~has_ref[si]
            q_ref[si[new]] = q[new]
            has_ref[si[new]] = True
            sign = torch.where((q * q_ref[si]).sum(1) < 0, -1.0, 1.0).double()
            q_sum.index_add_(0, si, (w * sign)[:, None] * q)
            c = g.colors[i].double()
            if cam is view_cam:
                baked_dc[si] = c
            d = all_means[si] - torch.as_tensor(cam.center, **f64)
            d = d / d.norm(dim=1, keepdim=True).clamp_min(1e-12)
            Y = _sh_basis(degree, d)
            A.index_add_(0, si, w[:, None, None] * Y[:, :, None] * Y[:, None, :])
            b.index_add_(0, si, w[:, None, None] * Y[:, :, None] * (c - 0.5)[:, None, :])

    # mean gated opacity over the views that see it (w_sum: the sum of o * g, > 0 exactly where it was shown)
    opacity = torch.where(seen > 0, w_sum / seen.clamp_min(1), torch.zeros_like(w_sum))
    keep = (opacity >= cfg.min_opacity) & (w_sum > 0)
    idx = keep.nonzero().squeeze(1)
    ws = w_sum[idx]
    reg = torch.full((nc,), cfg.ridge, **f64)
    reg[0] = 1e-9
    Ak = A[idx] + (ws[:, None, None] * torch.diag(reg)[None])
    coef = torch.linalg.solve(Ak, b[idx])  # [n, nc, 3]
    # SH coefficients as 3DGS stores them: colour = Y . coef + 0.5, with Y[0] = C0.
    if cfg.view is not None:  # that camera's colours where it sees the Gaussian, the fitted DC elsewhere
        dc = baked_dc[idx]
        dc = torch.where(torch.isnan(dc), coef[:, 0, :] * SH_C0 + 0.5, dc)
        coef = ((dc - 0.5) / SH_C0)[:, None, :]
    q = q_sum[idx]
    qn = q.norm(dim=1, keepdim=True)
    q = torch.where(qn > 1e-12, q / qn.clamp_min(1e-12), torch.tensor([1.0, 0.0, 0.0, 0.0], **f64))
    op = opacity[idx].clamp(1e-6, 1 - 1e-6)
    ply = GaussianPly(
        means=all_means[idx].float().cpu().numpy(),
        sh=coef.float().cpu().numpy(),
        opacities=torch.log(op / (1 - op)).float().cpu().numpy(),
        scales=(ls_sum[idx] / ws[:, None]).float().cpu().numpy(),
        quats=q.float().cpu().numpy(),
        has_normals=True,
    )
    info = {
        "xi": float(cfg.xi),
        "colour": f"view {cfg.view}" if cfg.view is not None else f"sh{degree}",
        "sh_degree": degree,
        "views": len(views),
        "anchors": M,
        "slots": S,
        "gaussians": int(idx.shape[0]),
        "never_shown": int(S - int((w_sum > 0).sum())),
        "below_min_opacity": int(((w_sum > 0) & ~keep).sum()),
        "config": asdict(cfg),
    }
    return Baked(ply, info)


# ================================================================================================ measure
def export_psnr(model, ply: GaussianPly, xi: float, cameras: list[Camera]) -> list[float]:
    """PSNR of ``ply`` rendered as plain 3DGS (our renderer, no gate) against ``model``'s own render, each camera
    at ``xi``."""
    from .explicit import ExplicitModel
    from .metrics import psnr

    ex = ExplicitModel(ply, tuple(model.background))
    out = []
    for cam in cameras:
        a = model.render(cam, xi).image
        e = ex.render(cam, xi).image
        out.append(psnr(e.clamp(0, 1), a.clamp(0, 1)))
    return out


# ================================================================================================ write
def write_gaussians(path: str | os.PathLike, ply: GaussianPly, fmt: str | None = None) -> int:
    """Write ``ply`` as a 3DGS PLY, an SPZ or a GLB (``fmt``, else the suffix); returns the file's bytes.

    SPZ's anti-aliased flag and the GLB's are left off: the coverage gate is baked into the opacities for one
    resolution, and a viewer's own anti-aliasing compensation would dim small Gaussians a second time (SPEC 13)."""
    p = Path(path)
    fmt = (fmt or p.suffix.lstrip(".")).lower()
    if fmt == "ply":
        from .formats.inria_ply import write_inria_ply

        write_inria_ply(p, ply)
    elif fmt == "spz":
        from .formats.spz import write_spz

        write_spz(p, ply, antialiased=False, fractional_bits=spz_fractional_bits(ply.means))
    elif fmt == "glb":
        from .formats.gltf import write_glb

        write_glb(p, ply, antialiased=False, y_up=True)  # glTF is y-up: splat-transform's 180 degrees about z
    else:
        raise ProxycodecError(f"unknown export format {fmt!r} (one of {', '.join(FORMATS)})", p)
    return p.stat().st_size


def spz_fractional_bits(means: np.ndarray, preferred: int = 12) -> int:
    """SPZ's fixed-point positions hold 24 signed bits: ``preferred`` (the reference writers' 12) fractional bits
    where the scene fits, fewer where its coordinates reach 2^(23 - 12) = 2048 units."""
    m = float(np.abs(means).max()) if len(means) else 0.0
    bits = preferred
    while bits > 0 and m * 2.0 ** bits >= 2.0 ** 23 - 1:
        bits -= 1
    return bits


def parse_levels(text: str) -> tuple[float, ...]:
    """``"1,0.5,0.25"`` -> (1.0, 0.5, 0.25): distinct resolution ratios, finest first."""
    try:
        levels = [check_xi(float(x)) for x in str(text).split(",") if x.strip()]
    except ValueError:
        raise ProxycodecError(f"--levels takes comma-separated resolution ratios, got {text!r}") from None
    if not levels:
        raise ProxycodecError("--levels is empty")
    if len(set(levels)) != len(levels):
        raise ProxycodecError(f"--levels repeats a resolution: {text!r}")
    return tuple(sorted(levels, reverse=True))


def write_lod(model, out_dir: str | os.PathLike, levels=DEFAULT_LEVELS, *, fmt: str = "spz", sh_degree: int = 1,
              directions: int | None = None, source: str = "", log=None) -> dict:
    """One file per level, each ``bake``d for its resolution, plus the manifest ``lod.json`` (SPEC 13); returns it.

    The manifest borrows the field names of splat-transform's Streamed SOG ``lod-meta.json`` (``count``, ``counts``,
    ``lodLevels``, ``filenames``; LOD 0 the finest) and adds, per level, its resolution, ``distance_scale`` (1 / xi)
    and bytes. Files are written to temporary names and renamed; the manifest last."""
    from .fileio import write_bytes_atomic

    if fmt not in FORMATS:
        raise ProxycodecError(f"unknown LOD format {fmt!r} (one of {', '.join(FORMATS)})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    entries = []
    for lod, xi in enumerate(levels):
        baked = bake(model, BakeConfig(xi=xi, sh_degree=sh_degree, directions=directions))
        name = f"lod{lod}.{fmt}"
        nbytes = write_gaussians(out / name, baked.ply, fmt)
        m = baked.ply.means
        bound = {"min": m.min(0).tolist(), "max": m.max(0).tolist()} if len(m) else {"min": [0] * 3, "max": [0] * 3}
        entries.append({"lod": lod, "resolution": float(xi), "distance_scale": 1.0 / float(xi), "file": name,
                        "count": baked.ply.n_gaussians, "bytes": nbytes, "bound": bound})
        if log:
            log(f"LOD {lod}: resolution {xi:g}: {baked.ply.n_gaussians} Gaussians, {nbytes} B -> {out / name}")
    from . import __version__

    manifest = {
        "version": 1,
        "asset": {"generator": f"proxycodec {__version__}"},
        "format": fmt,
        "source": source,
        "sh_degree": int(sh_degree),
        "count": int(sum(e["count"] for e in entries)),
        "counts": [e["count"] for e in entries],
        "lodLevels": len(entries),
        "filenames": [e["file"] for e in entries],
        "levels": entries,
    }
    write_bytes_atomic(out / LOD_MANIFEST, (json.dumps(manifest, indent=1) + "\n").encode())
    return manifest
