"""The built-in default scene: procedural, deterministic, a few thousand anchors, structure at several scales.

A tartan floor with a fine line grid, a banded sphere, a box with a diagonal lattice on its faces and a ring of
thin striped posts, z up, inside [-1.2, 1.2]^2 x [0, 0.9]. Surfaces are sampled densely, voxelised into anchors
(Scaffold-GS's rule: unique rounded positions), and each anchor gets 10 offsets on its local surface patch.

No training is needed: the decoder's MLPs are set analytically so features mean something a person can check.
Colour is a function of the anchor (its 10 Gaussians share it), built from features that a proxy predicts well:
- features 0..2: the part's base colour (RGB logits; constant on a part);
- features 3..18: per pattern a phase pair (sin, cos)(2 pi n / m), n = the anchor's integer grid coordinates
  along the pattern's integer direction, m its period in voxels (on other parts (-2, 0), where the stripe is off).
  A leaf's pair is its proxy's turned by an angle that depends only on the offset between them, which the
  residual predictor learns (a stripe pattern stored as a colour would not be predictable across its edges);
- features 19..21: the surface normal (n_x, n_y, 1 + n_z); feature 22: 1 on the posts (round Gaussians);
- features 23..31: a smooth function of position (as trained features are: correlated with their neighbours),
  which no MLP reads.
Networks:
- colour MLP: hidden units 0..2 pass the base logits through (ReLU(f + 4), undone by the output bias); per pattern
  two units whose difference clamp(k (s - hi) + 1, 0, 1) is a step of the phase's sine s, its ramp in the middle of
  the gap between two of the values s takes on the voxel grid (so a small error in a predicted phase moves no
  colour), times the pattern's RGB logit increment;
- covariance MLP: the quaternion turning z onto the normal (features 19..21 through ReLU(f + 20)); tangent scales
  sigmoid(0) = 0.5, normal scale sigmoid(-4) (sigmoid(0) on the posts: thinner than a voxel, their normals are
  noise), times the anchor base scale;
- opacity MLP: a constant tanh(3) = 0.995.
Every weight matrix is on the grid of the container's int8 weights (per-row scale max / 127) and every bias is a
float16, so the default weight quantisation stores the decoder exactly. FiLM starts (and stays) the identity; the
coverage gate is on.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .camera import Camera, orbit_cameras
from .decoder import DecoderConfig, GaussianDecoder
from .model import SceneModel
from .scene import AnchorScene
from .errors import ProxycodecError
from .sections import DEFAULT_WEIGHTS_DTYPE, weights_from_sections, weights_to_sections
from .weights import load_state_arrays

VOXEL = 0.04
K = 10
FLOOR, SPHERE, BOX, POSTS = range(4)
#: Base colour of each part (RGB in 0..1).
BASE = ((0.22, 0.25, 0.33), (0.95, 0.62, 0.12), (0.55, 0.13, 0.5), (0.1, 0.08, 0.08))
SPHERE_C, SPHERE_R = (-0.35, 0.3, 0.42), 0.38
BOX_C, BOX_H = (0.55, -0.45, 0.25), 0.25
#: Stripe patterns: (part, integer direction, period in voxels, where the step sits (a value of the sine, moved to
#: the middle of the gap that holds it), RGB logit increment where the stripe is on).
PATTERNS = (
    (FLOOR, (1, 0, 0), 16, 0.2, (2.4, 1.9, 0.9)),  # tartan, 0.64 wide
    (FLOOR, (0, 1, 0), 16, 0.2, (0.7, 1.6, 2.0)),
    (FLOOR, (1, 0, 0), 4, 0.5, (-1.6, -1.6, -1.2)),  # line grid every 4 voxels, one voxel wide
    (FLOOR, (0, 1, 0), 4, 0.5, (-1.6, -1.6, -1.2)),
    (SPHERE, (0, 0, 1), 5, 0.3, (-4.5, -0.8, 3.2)),  # bands
    (BOX, (1, 1, 1), 8, 0.4, (2.2, 3.4, 2.0)),  # a diagonal lattice
    (BOX, (1, -1, 1), 8, 0.4, (2.2, 3.4, 2.0)),
    (POSTS, (0, 0, 1), 5, 0.3, (4.6, 4.7, 4.7)),  # stripes
)
OFF = -2.0  # a pattern's sine on the other parts: below every step
N_FEAT = 32
NORMAL = 3 + 2 * len(PATTERNS)  # 19..21
ROUND = NORMAL + 3  # 22: 1 on the posts
SMOOTH = ROUND + 1  # 23..31
BASE_SHIFT = 4.0  # colour pass-through: ReLU(f + 4) for base logits in [-3.9, 3.9]
SHIFT = 20.0  # normal pass-through


def _floor(rng, n):
    p = np.c_[rng.uniform(-1.2, 1.2, (n, 2)), np.zeros(n)]
    p = p[~(np.abs(p[:, :2] - np.asarray(BOX_C[:2])) < BOX_H - VOXEL).all(1)]  # none under the box
    return p, np.tile([0.0, 0.0, 1.0], (len(p), 1))


def _sphere(rng, n, c=SPHERE_C, r=SPHERE_R):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] > -0.95]
    return np.asarray(c) + r * v, v


def _box(rng, n, c=BOX_C, h=BOX_H):
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
    return (np.asarray(c) + p)[keep], nrm[keep]


def _posts(rng, n, count=8, radius=0.02, height=0.8, ring=0.95):
    k = rng.integers(0, count, n)
    ang = 2 * math.pi * k / count + 0.2
    base = np.c_[ring * np.cos(ang), ring * np.sin(ang), np.zeros(n)]
    t = rng.uniform(0, 2 * math.pi, n)
    nrm = np.c_[np.cos(t), np.sin(t), np.zeros(n)]
    p = base + radius * nrm
    p[:, 2] = rng.uniform(0, height, n)
    return p, nrm


def _logit(x):
    x = np.clip(np.asarray(x, dtype=np.float64), 0.02, 0.98)
    return np.log(x / (1 - x))


def _ramp(period: int, target: float) -> tuple[float, float]:
    """(lo, hi): the middle 60% of the gap between the values of sin(2 pi n / period) (n integer) holding
    ``target``: where a pattern's step rises from off to on."""
    v = np.unique(np.round(np.sin(2 * np.pi * np.arange(period) / period), 12))
    i = int(np.searchsorted(v, target))
    lo, hi = v[i - 1], v[i]
    return float(lo + 0.2 * (hi - lo)), float(hi - 0.2 * (hi - lo))


def sample_scene(seed: int = 0, voxel: float = VOXEL) -> AnchorScene:
    rng = np.random.default_rng(seed)
    parts = [_floor(rng, 400_000), _sphere(rng, 90_000), _box(rng, 60_000), _posts(rng, 20_000)]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([n for _, n in parts])
    part = np.concatenate([np.full(len(p), i) for i, (p, _) in enumerate(parts)])
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
    g_nrm = nrm[sel].mean(1)
    g_nrm /= np.maximum(np.linalg.norm(g_nrm, axis=1, keepdims=True), 1e-9)
    votes = np.zeros((M, len(parts)))
    np.add.at(votes, (inv, part), 1)
    apart = votes.argmax(1)  # each anchor's part: the one most of its points lie on (ties to the first)

    feats = np.zeros((M, N_FEAT))
    feats[:, 0:3] = _logit(BASE)[apart]
    for j, (on_part, direction, period, _, _) in enumerate(PATTERNS):
        th = 2 * math.pi * (uniq @ np.asarray(direction)) / period  # exact: integer grid coordinates
        on = apart == on_part
        feats[:, 3 + 2 * j] = np.where(on, np.sin(th), OFF)
        feats[:, 4 + 2 * j] = np.where(on, np.cos(th), 0.0)
    feats[:, NORMAL] = g_nrm[:, 0]
    feats[:, NORMAL + 1] = g_nrm[:, 1]
    feats[:, NORMAL + 2] = 1.0 + g_nrm[:, 2]
    feats[:, ROUND] = apart == POSTS
    n_smooth = N_FEAT - SMOOTH
    freq = rng.normal(size=(n_smooth, 3)) * 3.0
    feats[:, SMOOTH:] = 0.5 * np.sin(anchors @ freq.T + rng.uniform(0, 2 * math.pi, n_smooth))
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


def _on_storage_grid(decoder: GaussianDecoder) -> None:
    """Put the decoder through the container's weight storage at encode's default precision
    (``sections.weights_to_sections``, then ``weights_from_sections``: q7 matrices, float16 vectors), so that storing
    it with the defaults changes nothing."""
    stored = weights_to_sections("decoder", decoder.state_arrays(), DEFAULT_WEIGHTS_DTYPE)
    load_state_arrays(decoder, weights_from_sections("decoder", stored, ProxycodecError), "sample decoder")


def sample_decoder(scene: AnchorScene) -> GaussianDecoder:
    meta = scene.metadata
    cfg = DecoderConfig(scene_center=tuple(meta.get("center", (0, 0, 0))), scene_radius=float(meta.get("radius", 1.0)))
    # The layers not set below (the FiLM MLP's first layer) keep torch's random init: draw it from the scene's seed,
    # so the same seed gives the same bytes (the FiLM output layer is zero, so it does not change any render).
    with torch.random.fork_rng():
        torch.manual_seed(int(meta.get("seed", 0)))
        dec = GaussianDecoder(cfg)
    with torch.no_grad():
        for mlp in (dec.mlp_opacity, dec.mlp_cov, dec.mlp_color):
            for p in mlp.parameters():
                p.zero_()
        dec.mlp_opacity[2].bias[:] = 3.0
        # colour: hidden 0..2 = ReLU(base + BASE_SHIFT); per pattern j, hidden 3 + 2j, 4 + 2j make its step
        w1, b1 = dec.mlp_color[0].weight, dec.mlp_color[0].bias
        w2, b2 = dec.mlp_color[2].weight, dec.mlp_color[2].bias
        inc = np.zeros((3 + 2 * len(PATTERNS), 3))
        for ch in range(3):
            w1[ch, ch] = 1.0
            b1[ch] = BASE_SHIFT
            inc[ch, ch] = 1.0
        for j, (_, _, period, target, rgb) in enumerate(PATTERNS):
            lo, hi = _ramp(period, target)
            h, slope = 3 + 2 * j, 1.0 / (hi - lo)
            w1[h, 3 + 2 * j] = w1[h + 1, 3 + 2 * j] = slope
            b1[h] = 1.0 - slope * hi  # ReLU(slope (s - hi) + 1) - ReLU(slope (s - hi)) = clamp(., 0, 1)
            b1[h + 1] = -slope * hi
            inc[h], inc[h + 1] = rgb, -np.asarray(rgb)
        for k in range(K):
            w2[3 * k:3 * k + 3, :len(inc)] = torch.tensor(inc.T, dtype=torch.float32)
            b2[3 * k:3 * k + 3] = -BASE_SHIFT
        # covariance: hidden 0..2 = ReLU(normal + SHIFT), hidden 3 = ReLU(round + SHIFT)
        w, b = dec.mlp_cov[0].weight, dec.mlp_cov[0].bias
        for i in range(3):
            w[i, NORMAL + i] = 1.0
        w[3, ROUND] = 1.0
        b[:4] = SHIFT
        w, b = dec.mlp_cov[2].weight, dec.mlp_cov[2].bias
        for k in range(K):
            o = 7 * k
            b[o:o + 2] = 0.0  # tangent scale logits
            w[o + 2, 3] = 4.0  # normal scale logit: -4, or 0 on the posts
            b[o + 2] = -4.0 - 4.0 * SHIFT
            w[o + 3, 2] = 1.0  # w = 1 + n_z
            w[o + 4, 1] = -1.0  # x = -n_y
            w[o + 5, 0] = 1.0  # y = n_x
            b[o + 3] = -SHIFT
            b[o + 4] = SHIFT
            b[o + 5] = -SHIFT
    _on_storage_grid(dec)
    return dec.eval()


def sample_cameras(n: int = 8, width: int = 256, height: int = 192) -> list[Camera]:
    return orbit_cameras((0.0, 0.0, 0.25), 3.2, n, elevation_deg=32.0, fov_x_deg=50.0, width=width, height=height)


def sample_model(seed: int = 0) -> SceneModel:
    scene = sample_scene(seed)
    return SceneModel(scene, sample_decoder(scene), sample_cameras(), (1.0, 1.0, 1.0))
