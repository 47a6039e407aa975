"""The built-in default scene: procedural, deterministic, a few thousand anchors, structure at several scales.

A checkerboard floor with a fine line grid, a striped sphere, a box with nested squares on its faces and a ring of
thin posts, z up, inside [-1.2, 1.2]^2 x [0, 0.9]. Surfaces are sampled densely, voxelised into anchors (Scaffold-GS's
rule: unique rounded positions), and each anchor gets 10 offsets on its local surface patch.

No training is needed: the decoder's MLPs are set analytically so features mean something a person can check.
Hidden units pass features through (ReLU(f + S) with a shift S that keeps them positive, undone by the output
bias), so
- color MLP: Gaussian k's color = sigmoid(base_rgb + lum_k), from features 0..2 (base) and 3..12 (lum);
- covariance MLP: the quaternion turning z onto the surface normal from features 13..15 (n_x, n_y, 1 + n_z);
  tangent scales sigmoid(0) = 0.5, normal scale sigmoid(-4), times the anchor base scale;
- opacity MLP: a constant tanh(3) = 0.995.
Features 16..31 carry a smooth function of position (as trained features do: correlated with their neighbours).
FiLM starts (and stays) the identity; the coverage gate is on.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .camera import Camera, orbit_cameras
from .decoder import DecoderConfig, GaussianDecoder
from .model import SceneModel
from .scene import AnchorScene

SHIFT = 20.0
VOXEL = 0.04
K = 10


def _floor(rng, n):
    p = np.c_[rng.uniform(-1.2, 1.2, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    check = (np.floor(p[:, 0] / 0.3) + np.floor(p[:, 1] / 0.3)) % 2
    col = np.where(check[:, None] > 0, [0.85, 0.82, 0.75], [0.25, 0.3, 0.4])
    fine = (np.abs((p[:, :2] / 0.075) - np.round(p[:, :2] / 0.075)) < 0.12).any(1)  # thin grid lines
    col = np.where(fine[:, None], [0.55, 0.1, 0.1], col)
    return p, nrm, col


def _sphere(rng, n, c=(-0.35, 0.3, 0.42), r=0.38):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] > -0.95]
    lat = np.arcsin(v[:, 2])
    stripes = (np.floor(lat / (math.pi / 12)) % 2)[:, None]
    lon = np.arctan2(v[:, 1], v[:, 0])
    col = np.where(stripes > 0, [0.95, 0.7, 0.1], [0.1, 0.45, 0.85])
    col = col * (0.75 + 0.25 * np.cos(6 * lon))[:, None]
    return np.asarray(c) + r * v, v, col


def _box(rng, n, c=(0.55, -0.45, 0.25), h=0.25):
    face = rng.integers(0, 6, n)
    uv = rng.uniform(-h, h, (n, 2))
    axis, sign = face // 2, np.where(face % 2 == 0, 1.0, -1.0)
    p = np.zeros((n, 3))
    nrm = np.zeros((n, 3))
    for a in range(3):
        m = axis == a
        others = [i for i in range(3) if i != a]
        p[m, a] = sign[m] * h
        p[m, others[0]] = uv[m, 0]
        p[m, others[1]] = uv[m, 1]
        nrm[m, a] = sign[m]
    keep = ~((axis == 2) & (sign < 0))  # no bottom face (it sits on the floor)
    ring = np.maximum(np.abs(uv[:, 0]), np.abs(uv[:, 1]))
    nested = (np.floor(ring / 0.04) % 2)[:, None]
    col = np.where(nested > 0, [0.9, 0.9, 0.92], [0.6, 0.15, 0.55])
    return (np.asarray(c) + p)[keep], nrm[keep], col[keep]


def _posts(rng, n, count=8, radius=0.02, height=0.8, ring=0.95):
    k = rng.integers(0, count, n)
    ang = 2 * math.pi * k / count + 0.2
    base = np.c_[ring * np.cos(ang), ring * np.sin(ang), np.zeros(n)]
    t = rng.uniform(0, 2 * math.pi, n)
    nrm = np.c_[np.cos(t), np.sin(t), np.zeros(n)]
    p = base + radius * nrm
    p[:, 2] = rng.uniform(0, height, n)
    col = np.where(((p[:, 2] / 0.1).astype(int) % 2)[:, None] > 0, [0.95, 0.95, 0.95], [0.05, 0.05, 0.05])
    return p, nrm, col


def _logit(x):
    x = np.clip(x, 0.02, 0.98)
    return np.log(x / (1 - x))


def sample_scene(seed: int = 0, voxel: float = VOXEL) -> AnchorScene:
    rng = np.random.default_rng(seed)
    parts = [_floor(rng, 400_000), _sphere(rng, 90_000), _box(rng, 60_000), _posts(rng, 20_000)]
    pts = np.concatenate([p for p, _, _ in parts])
    nrm = np.concatenate([n for _, n, _ in parts])
    col = np.concatenate([c for _, _, c in parts])
    cells = np.round(pts / voxel).astype(np.int64)
    uniq, inv = np.unique(cells, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    M = len(uniq)
    order = np.lexsort((rng.random(len(pts)), inv))  # points grouped by anchor, random within
    starts = np.searchsorted(inv[order], np.arange(M))
    counts = np.bincount(inv, minlength=M)
    take = starts[:, None] + (np.arange(K)[None, :] % counts[:, None])  # K samples per anchor (repeat if fewer)
    sel = order[take]  # [M, K]
    anchors = uniq * voxel
    offsets = (pts[sel] - anchors[:, None, :]) / voxel
    g_col = col[sel]  # [M, K, 3]
    g_nrm = nrm[sel].mean(1)
    g_nrm /= np.maximum(np.linalg.norm(g_nrm, axis=1, keepdims=True), 1e-9)

    logits = _logit(g_col)  # [M, K, 3]
    base = logits.mean(1)  # [M, 3]
    lum = (logits - base[:, None, :]).mean(2)  # [M, K]
    feats = np.zeros((M, 32))
    feats[:, 0:3] = base
    feats[:, 3:13] = lum
    feats[:, 13] = g_nrm[:, 0]
    feats[:, 14] = g_nrm[:, 1]
    feats[:, 15] = 1.0 + g_nrm[:, 2]
    freq = rng.normal(size=(16, 3)) * 3.0
    feats[:, 16:32] = 0.5 * np.sin(anchors @ freq.T + rng.uniform(0, 2 * math.pi, 16))
    scal = np.zeros((M, 6))
    scal[:, 0:3] = math.log(voxel)
    scal[:, 3:6] = math.log(voxel * 0.7)
    c = anchors.mean(0)
    r = float(np.linalg.norm(anchors - c, axis=1).max())
    return AnchorScene(
        positions=torch.tensor(anchors, dtype=torch.float32),
        features=torch.tensor(feats, dtype=torch.float32),
        offsets=torch.tensor(offsets, dtype=torch.float32),
        scalings=torch.tensor(scal, dtype=torch.float32),
        voxel_size=voxel,
        metadata={"name": "proxycodec-sample", "seed": seed, "center": c.tolist(), "radius": r},
    ).validate()


def sample_decoder(scene: AnchorScene) -> GaussianDecoder:
    meta = scene.metadata
    cfg = DecoderConfig(scene_center=tuple(meta.get("center", (0, 0, 0))), scene_radius=float(meta.get("radius", 1.0)))
    # The layers not set below (the FiLM MLP's first layer) keep torch's random init: draw it from the scene's seed,
    # so the same seed gives the same bytes (the FiLM output layer is zero, so it does not change any render).
    with torch.random.fork_rng():
        torch.manual_seed(int(meta.get("seed", 0)))
        dec = GaussianDecoder(cfg)
    F = cfg.feat_dim
    with torch.no_grad():
        for mlp in (dec.mlp_opacity, dec.mlp_cov, dec.mlp_color):
            for p in mlp.parameters():
                p.zero_()
            mlp[0].weight[:, :F] = torch.eye(32, F)  # hidden j = ReLU(f_j + S)
            mlp[0].bias[:] = SHIFT
        dec.mlp_opacity[2].bias[:] = 3.0
        w, b = dec.mlp_color[2].weight, dec.mlp_color[2].bias
        for k in range(K):
            for ch in range(3):
                w[3 * k + ch, ch] = 1.0
                w[3 * k + ch, 3 + k] = 1.0
                b[3 * k + ch] = -2 * SHIFT
        w, b = dec.mlp_cov[2].weight, dec.mlp_cov[2].bias
        for k in range(K):
            o = 7 * k
            b[o:o + 2] = 0.0  # tangent scale logits
            b[o + 2] = -4.0  # normal scale logit
            w[o + 3, 15] = 1.0  # w = 1 + n_z
            w[o + 4, 14] = -1.0  # x = -n_y
            w[o + 5, 13] = 1.0  # y = n_x
            b[o + 3] = -SHIFT
            b[o + 4] = SHIFT
            b[o + 5] = -SHIFT
    return dec.eval()


def sample_cameras(n: int = 8, width: int = 256, height: int = 192) -> list[Camera]:
    return orbit_cameras((0.0, 0.0, 0.25), 3.2, n, elevation_deg=32.0, fov_x_deg=50.0, width=width, height=height)


def sample_model(seed: int = 0) -> SceneModel:
    scene = sample_scene(seed)
    return SceneModel(scene, sample_decoder(scene), sample_cameras(), (1.0, 1.0, 1.0))
