"""Torch-free decode + render: a container -> one view, with numpy and the numba kernels only.

Why: ``proxycodec decode scene.pxc --res 0.3 --view 0`` should take well under 2 s end to end in a fresh process
on a 2-core machine (issue 5), and importing torch alone costs ~1.3 s there, plus ~0.4 s of first-call overheads in
the small MLPs. The networks involved at decode time are tiny (a few 32-64 wide layers), so numpy runs them as fast.

What it does is exactly what the torch path does (``codec.decode`` then ``SceneModel.render`` with the ``cpu``
backend), step by step:

- the container is read and dequantised by the same code (``sections.py``): positions, scalings, offsets and the
  proxies' features are bit-identical to ``codec.decode``'s, and a malformed file raises the same ``ContainerError``;
- leaves are regenerated with the residual predictor (``proxy.ResidualPredictor.predict``: positional encodings of
  the proxy -> leaf distance and direction, encoder, residual blocks, head) written in numpy, from the same nearest
  proxies (``nearest.py``), in the same chunks;
- the view is decoded as ``model.decode_view`` does: frustum culling of the anchors' bounding spheres
  (``decoder.visible_anchors``), the resolution embedding (FiLM / additive / none, xi clamped to
  ``film_xi_range``), an imported Scaffold-GS decoder's variants (feature bank, MLPs without the distance input)
  and the opacity / covariance / colour MLPs (``GaussianDecoder.forward``);
- projection (with the pixel coverage gate) and compositing call the very numba kernels behind the ``cpu`` backend
  (``render/_project_kernels.py``, ``render/_raster_kernels.py``) on numpy arrays.

float32 matrix products and transcendental functions in numpy are not bit-identical to torch's (and which way they
round depends on the machine's BLAS kernels), so regenerated leaf features agree to ~1e-7 relative, the Gaussians'
parameters to float32 rounding, and images to ~1e-6 except where a value within that rounding of a threshold is
decided differently (a whole Gaussian then shows at a pixel in one image only). Given the same Gaussians
(``LiteScene.composite``), projection and compositing give the torch path's bits. tests/test_decode_lite.py
checks each stage (SPEC.md, "Portability").

Only the residual predictor is implemented; ``decode`` raises ``Unsupported`` for other predictor kinds, and
callers (the CLI) then take the torch path.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera, check_xi
from .camera import default_cameras as _default_cameras
from .formats.container import ContainerError
from .nearest import predictor_neighbours
from .netconfig import DecoderConfig, PredictorConfig
from .render._project_kernels import constants, project_forward
from .render._raster_kernels import rasterize_forward
from .sections import (
    PREDICT_CHUNK,
    guarded,
    read_scene_container,
    scene_extras,
    stored_anchors,
    weights_from_sections,
)
from .weights import check_arrays

__all__ = ["Unsupported", "LiteScene", "LiteRender", "decode", "default_cameras", "image_to_uint8"]

_F32 = np.float32
NEAR = 0.01  # the near plane of ``decoder.visible_anchors`` and ``render.project`` (their defaults)
FAR = 1e10


class Unsupported(Exception):
    """The container uses something this path does not implement (the torch path, ``codec.decode``, does)."""


# ---------------------------------------------------------------------------------------------- layers
#: Multiply-adds per matrix product below which OpenBLAS stays on the calling thread (its SMP threshold,
#: 65536 x GEMM_MULTITHREAD_THRESHOLD = 4). Products are split into row blocks of about this size: these layers are
#: far too small to gain from threads, and on a loaded 2-core machine OpenBLAS's second thread made the decoder
#: 4-10x slower (10 ms -> 40-130 ms for lego's 3.4k anchors), as torch's intra-op threads did (``proxy.torch_threads``).
_GEMM_SERIAL_WORK = 65536 * 4


def _linear(x: np.ndarray, w: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """torch.nn.Linear: x @ W^T + b (float32), in row blocks that each run on one thread."""
    W, b = w
    rows = max(16, _GEMM_SERIAL_WORK // max(1, W.shape[0] * W.shape[1]))
    if x.shape[0] <= rows:
        return x @ W.T + b
    out = np.empty((x.shape[0], W.shape[0]), dtype=np.result_type(x, W))
    for s in range(0, x.shape[0], rows):
        np.matmul(x[s:s + rows], W.T, out=out[s:s + rows])
    out += b
    return out


def _relu(x: np.ndarray) -> np.ndarray:
    return np.maximum(x, _F32(0.0))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return _F32(1.0) / (_F32(1.0) + np.exp(-x))


def _softmax(x: np.ndarray) -> np.ndarray:
    """torch.softmax(x, dim=1)."""
    e = np.exp(x - x.max(1, keepdims=True))
    return e / e.sum(1, keepdims=True)


def _mlp(x: np.ndarray, layers) -> np.ndarray:
    """``decoder._mlp``: Linear, ReLU, Linear."""
    return _linear(_relu(_linear(x, layers[0])), layers[1])


def _norm(v: np.ndarray) -> np.ndarray:
    """[N, 3] -> [N, 1] Euclidean norms (float32), torch's ``v.norm(dim=1, keepdim=True)``."""
    return np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]


def positional_encoding(x: np.ndarray, n_freqs: int) -> np.ndarray:
    """``decoder.positional_encoding``: [x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs (float32)."""
    if n_freqs == 0:
        return x
    freqs = (_F32(2.0) ** np.arange(n_freqs, dtype=_F32)) * _F32(math.pi)
    xf = x[..., None] * freqs  # [..., D, L]
    flat = xf.shape[:-2] + (xf.shape[-2] * xf.shape[-1],)
    return np.concatenate([x, np.sin(xf).reshape(flat), np.cos(xf).reshape(flat)], -1)


# ---------------------------------------------------------------------------------------------- networks
def _layer(arrays: dict[str, np.ndarray], prefix: str) -> tuple[np.ndarray, np.ndarray]:
    return arrays[f"{prefix}.weight"], arrays[f"{prefix}.bias"]


def _linear_shapes(prefix: str, n_in: int, n_out: int) -> dict[str, tuple[int, ...]]:
    return {f"{prefix}.weight": (n_out, n_in), f"{prefix}.bias": (n_out,)}


def predictor_shapes(cfg: PredictorConfig) -> dict[str, tuple[int, ...]]:
    """The state_dict layout of ``proxy.ResidualPredictor(cfg)``: names and shapes, in its order."""
    h = cfg.hidden
    out = _linear_shapes("encoder.0", cfg.n_in, h)
    for i in range(cfg.n_blocks):
        out.update(_linear_shapes(f"blocks.{i}.fc1", h, h))
        out.update(_linear_shapes(f"blocks.{i}.fc2", h, h))
    out.update(_linear_shapes("head", h, cfg.n_out))
    return out


def decoder_shapes(cfg: DecoderConfig) -> dict[str, tuple[int, ...]]:
    """The state_dict layout of ``decoder.GaussianDecoder(cfg)``: names and shapes, in its order."""
    F, K, h = cfg.feat_dim, cfg.n_offsets, cfg.hidden
    n_in = cfg.mlp_inputs()
    out: dict[str, tuple[int, ...]] = {}
    for name, n_out in (("mlp_opacity", K), ("mlp_cov", 7 * K), ("mlp_color", 3 * K)):
        out.update(_linear_shapes(f"{name}.0", n_in[name], h))
        out.update(_linear_shapes(f"{name}.2", h, n_out))
    if cfg.embedding != "none":
        n_pe = 3 * (1 + 2 * cfg.pe_pos_freqs) + (1 + 2 * cfg.pe_res_freqs)
        out.update(_linear_shapes("mlp_embed.0", n_pe, cfg.film_hidden))
        out.update(_linear_shapes("mlp_embed.2", cfg.film_hidden, 2 * F if cfg.embedding == "film" else F))
    if cfg.feature_bank:
        out.update(_linear_shapes("mlp_feature_bank.0", 4, cfg.feature_bank))
        out.update(_linear_shapes("mlp_feature_bank.2", cfg.feature_bank, 3))
    return out


class Predictor:
    """``proxy.ResidualPredictor`` (inference only) on numpy arrays."""

    def __init__(self, config: PredictorConfig, arrays: dict[str, np.ndarray]):
        self.config = config
        w = check_arrays(predictor_shapes(config), arrays, "predictor")
        self.encoder = _layer(w, "encoder.0")
        self.blocks = [(_layer(w, f"blocks.{i}.fc1"), _layer(w, f"blocks.{i}.fc2")) for i in range(config.n_blocks)]
        self.head = _layer(w, "head")

    def inputs(self, positions: np.ndarray, proxy_pos: np.ndarray) -> np.ndarray:
        """``proxy.predictor_inputs``: PE of the log distance and of the unit direction proxy -> leaf."""
        cfg = self.config
        v = positions - proxy_pos
        d = _norm(v)
        u = v / np.maximum(d, _F32(1e-12))
        s = np.log(np.maximum(d, _F32(1e-6 * cfg.dist_ref)) / _F32(cfg.dist_ref)) / _F32(4.0)
        return np.concatenate([positional_encoding(s, cfg.pe_dist_freqs), positional_encoding(u, cfg.pe_dir_freqs)],
                              -1)

    def predict(self, positions, features, nearest, leaves, offsets=None):
        """``ResidualPredictor.predict``: (features [L, F], offsets [L, K, 3] or None) of the anchors ``leaves``."""
        cfg = self.config
        near = nearest[:, None] if nearest.ndim == 1 else nearest
        kk = near[leaves]
        k = kk[:, 0]
        pf = features[k]
        parts = [pf, self.inputs(positions[leaves], positions[k])]
        for j in range(1, cfg.context):  # ``proxy.predictor_geometry``
            parts += [features[kk[:, j]] - pf, self.inputs(positions[leaves], positions[kk[:, j]])]
        x = _relu(_linear(np.concatenate(parts, -1), self.encoder))
        for fc1, fc2 in self.blocks:
            x = x + _linear(_relu(_linear(x, fc1)), fc2)
        out = _linear(x, self.head)
        feats = pf + out[:, :cfg.feat_dim]
        offs = None
        if cfg.predict_offsets:
            offs = offsets[k] + out[:, cfg.feat_dim:].reshape(-1, cfg.n_offsets, 3)
        return feats, offs


@dataclass
class Gaussians:
    """``decoder.NeuralGaussians`` as numpy arrays (means relative to ``origin``, the camera centre)."""

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    anchor_index: np.ndarray
    origin: np.ndarray  # [3] float32
    slot: np.ndarray | None = None  # [N] which of the K offsets (``NeuralGaussians.slot``)

    @property
    def count(self) -> int:
        return int(self.means.shape[0])


class Decoder:
    """``decoder.GaussianDecoder`` (inference only) on numpy arrays."""

    def __init__(self, config: DecoderConfig, arrays: dict[str, np.ndarray]):
        self.config = config
        w = check_arrays(decoder_shapes(config), arrays, "decoder")
        self.opacity = (_layer(w, "mlp_opacity.0"), _layer(w, "mlp_opacity.2"))
        self.cov = (_layer(w, "mlp_cov.0"), _layer(w, "mlp_cov.2"))
        self.color = (_layer(w, "mlp_color.0"), _layer(w, "mlp_color.2"))
        self.embedding = (_layer(w, "mlp_embed.0"), _layer(w, "mlp_embed.2")) if config.embedding != "none" else None
        self.bank = (_layer(w, "mlp_feature_bank.0"), _layer(w, "mlp_feature_bank.2")) if config.feature_bank \
            else None

    def embed(self, positions: np.ndarray, features: np.ndarray, xi: float) -> np.ndarray:
        """``GaussianDecoder.embed``: f_hat = (1 + gamma) f + beta (FiLM), f + beta (additive) or f (none)."""
        cfg = self.config
        if cfg.embedding == "none" or features.shape[0] == 0:
            return features
        c = np.asarray(cfg.scene_center, dtype=_F32)
        xn = np.clip((positions - c) / _F32(cfg.scene_radius), _F32(-4.0), _F32(4.0))
        lo, hi = cfg.film_xi_range
        s = np.full((positions.shape[0], 1), math.log2(min(max(float(xi), lo), hi)) / 4.0, dtype=_F32)
        pe = np.concatenate([positional_encoding(xn, cfg.pe_pos_freqs), positional_encoding(s, cfg.pe_res_freqs)],
                            -1)
        out = _mlp(pe, self.embedding)
        if cfg.embedding == "additive":
            return features + out
        gamma, beta = out[:, :cfg.feat_dim], out[:, cfg.feat_dim:]
        return (_F32(1.0) + gamma) * features + beta

    def __call__(self, positions, features, offsets, scalings, camera_center: np.ndarray, xi: float) -> Gaussians:
        """``GaussianDecoder.forward``: Gaussians of positive opacity; covariance and colour only for anchors with
        at least one."""
        cfg = self.config
        K = cfg.n_offsets
        f_hat = self.embed(positions, features, xi)
        view = positions - camera_center
        dist = _norm(view)
        direction = view / np.maximum(dist, _F32(1e-12))
        dist = dist / _F32(cfg.length_unit)  # the MLPs' units (exact for 1)
        if self.bank is not None:  # ``GaussianDecoder.feature_bank``
            w = _softmax(_mlp(np.concatenate([direction, dist], -1), self.bank))
            f_hat = (np.tile(f_hat[:, ::4], (1, 4)) * w[:, :1] + np.tile(f_hat[:, ::2], (1, 2)) * w[:, 1:2]
                     + f_hat * w[:, 2:])
        x = np.concatenate([f_hat, direction, dist], -1)
        opacity = np.tanh(_mlp(x if cfg.opacity_dist else x[:, :-1], self.opacity))  # [M, K]
        mask = opacity > 0
        live = np.flatnonzero(mask.any(1))
        x, opacity, mask = x[live], opacity[live], mask[live]
        cov = _mlp(x if cfg.cov_dist else x[:, :-1], self.cov).reshape(-1, K, 7)
        color = _sigmoid(_mlp(x if cfg.color_dist else x[:, :-1], self.color)).reshape(-1, K, 3)
        sc = np.exp(scalings[live])  # [m, 6]
        scales = sc[:, None, 3:] * _sigmoid(cov[..., :3])
        means = view[live][:, None, :] + offsets[live] * sc[:, None, :3]
        a_idx, slot = np.nonzero(mask)
        return Gaussians(means=means[a_idx, slot], quats=cov[a_idx, slot, 3:], scales=scales[a_idx, slot],
                         opacities=opacity[a_idx, slot], colors=color[a_idx, slot], anchor_index=live[a_idx],
                         origin=camera_center, slot=slot)


def visible_anchors(positions: np.ndarray, radius: np.ndarray, camera: Camera, near: float = NEAR) -> np.ndarray:
    """``decoder.visible_anchors``: indices of anchors whose bounding sphere intersects the view frustum."""
    R = np.asarray(camera.rotation, dtype=_F32)
    t = np.asarray(camera.translation, dtype=_F32)
    p = positions @ R.T + t
    W, H, fx, fy, cx, cy = camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
    planes = np.array([[fx, 0.0, cx], [-fx, 0.0, W - cx], [0.0, fy, cy], [0.0, -fy, H - cy]], dtype=_F32)
    planes = planes / _norm(planes)
    inside = (p @ planes.T >= -radius[:, None]).all(1) & (p[:, 2] + radius > _F32(near))
    return np.flatnonzero(inside)


# ---------------------------------------------------------------------------------------------- scene
@dataclass
class Projected:
    """The rows of ``render.Projected`` the CLI reports (numpy)."""

    means2d: np.ndarray
    conics: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    depths: np.ndarray
    extent: np.ndarray
    index: np.ndarray
    gate: np.ndarray
    width: int
    height: int

    @property
    def count(self) -> int:
        return int(self.means2d.shape[0])


@dataclass
class LiteRender:
    """``model.SceneRender`` with numpy arrays: image [H, W, 3] float32 in [0, 1] (not clamped), alpha [H, W]."""

    image: np.ndarray
    alpha: np.ndarray
    projected: Projected
    gaussians: Gaussians
    visible_anchor_index: np.ndarray


@dataclass
class LiteScene:
    """A decoded scene (leaves regenerated) as numpy arrays, with numpy networks: renders views without torch."""

    positions: np.ndarray  # [M, 3] float32, stored (Morton) order
    features: np.ndarray  # [M, F]
    offsets: np.ndarray  # [M, K, 3]
    scalings: np.ndarray  # [M, 6] log
    voxel_size: float
    decoder: Decoder
    cameras: list[Camera] | None
    background: tuple[float, float, float]
    metadata: dict = field(default_factory=dict)  # the scene's, with ``proxy_mask``
    _radius: np.ndarray | None = field(default=None, repr=False)

    @property
    def num_anchors(self) -> int:
        return int(self.positions.shape[0])

    def bounds(self) -> np.ndarray:
        """[2, 3] float64 bounds of the anchor positions (``AnchorScene.bounds``)."""
        p = self.positions.astype(np.float64)
        return np.stack([p.min(0), p.max(0)]) if len(p) else np.zeros((2, 3))

    def extent_radius(self) -> np.ndarray:
        """``AnchorScene.extent_radius``: [M] radius of a sphere around each anchor holding its Gaussians."""
        if self._radius is None:
            s = self.scalings
            off = np.sqrt(((self.offsets * np.exp(s[:, None, :3])) ** 2).sum(-1)).max(1) if self.offsets.shape[1] \
                else _F32(0.0)
            self._radius = off + _F32(3.0) * np.exp(s[:, 3:]).max(1)
        return self._radius

    def render(self, camera: Camera, xi: float = 1.0, *, backend: str = "cpu") -> LiteRender:
        """``SceneModel.render(camera, xi, backend="cpu")`` (the camera given at its 100% reference size)."""
        if backend not in ("auto", "cpu"):
            raise ValueError(f"the torch-free path renders with the cpu backend only, not {backend!r}")
        xi = check_xi(xi)
        cam = camera.scaled(xi)
        g, vis = self.decode_view(cam, xi)
        return self.composite(g, cam, vis)

    def decode_view(self, cam: Camera, xi: float) -> tuple[Gaussians, np.ndarray]:
        """``model.decode_view``: the Gaussians of the anchors visible from ``cam`` (already at its render
        resolution), ``anchor_index`` into the whole scene, and the visible anchor indices."""
        vis = visible_anchors(self.positions, self.extent_radius(), cam, self.decoder.config.near_plane())
        center = np.asarray(cam.center, dtype=_F32)
        g = self.decoder(self.positions[vis], self.features[vis], self.offsets[vis], self.scalings[vis], center, xi)
        g.anchor_index = vis[g.anchor_index]
        return g, vis

    def composite(self, g: Gaussians, cam: Camera, vis: np.ndarray) -> LiteRender:
        """Projection (with the decoder's gate) and compositing of ``g`` into ``cam`` (at its render resolution):
        the numba kernels behind the ``cpu`` backend, so the same Gaussians give the torch path's bits."""
        gate = self.decoder.config.gate
        k = constants(cam, gate, self.decoder.config.near_plane(), FAR, np.asarray(g.origin, dtype=_F32).astype(np.float64),
                      _F32)
        c = np.ascontiguousarray
        m2d, con, op, dep, ext, g_val, idx = project_forward(c(g.means), c(g.quats), c(g.scales), c(g.opacities), k,
                                                             bool(gate.enabled))
        colors = c(g.colors[idx])
        proj = Projected(m2d, con, op, colors, dep, ext, idx, g_val, cam.width, cam.height)
        bg64 = np.asarray(self.background, dtype=_F32).astype(np.float64)  # a float32 tensor, widened, in torch
        W, H = cam.width, cam.height
        if proj.count == 0:
            image = np.broadcast_to(bg64, (H, W, 3)).astype(_F32)
            alpha = np.zeros((H, W), _F32)
        else:
            image, alpha, _, _, _ = rasterize_forward(m2d, con, op, colors, dep, ext, W, H, bg64)
        return LiteRender(image=image, alpha=alpha, projected=proj, gaussians=g, visible_anchor_index=vis)


def decode(path: str | os.PathLike) -> LiteScene:
    """``codec.decode`` without torch: read, verify and dequantise a scene container, regenerate its leaves.

    Raises ``ContainerError`` (a ``ProxycodecError``) for a malformed file, as ``codec.decode`` does, and
    ``Unsupported`` for a leaf predictor other than the residual one.
    """
    path = Path(path)
    c = read_scene_container(path)

    def err(m: str) -> ContainerError:
        return ContainerError(m, path)

    return guarded(_scene_from_sections, err, c.meta, dict(c.arrays), err)


def _scene_from_sections(meta: dict, sections: dict[str, np.ndarray], err) -> LiteScene:
    kind = meta.get("predictor", {}).get("kind", "residual") if isinstance(meta.get("predictor"), dict) else None
    if kind not in (None, "residual"):
        raise Unsupported(f"leaf predictor kind {kind!r}")
    a = stored_anchors(meta, sections, err)
    decoder = Decoder(a.decoder_config, weights_from_sections("decoder", sections, err))
    predictor = Predictor(a.predictor_config, weights_from_sections("predictor", sections, err))
    pos, feats, offs, mask = a.positions, a.features, a.offsets, a.proxy_mask
    leaves = np.flatnonzero(~mask)
    if leaves.size:
        nearest = predictor_neighbours(pos, mask, a.predictor_config)
        for s in range(0, leaves.size, PREDICT_CHUNK):
            lv = leaves[s:s + PREDICT_CHUNK]
            f_pred, o_pred = predictor.predict(pos, feats, nearest, lv, offs)
            feats[lv] = f_pred
            if o_pred is not None:
                offs[lv] = o_pred
    if not (np.all(np.isfinite(feats)) and np.all(np.isfinite(offs))):
        raise err("regenerated leaves are not finite")
    cams, bg, scene_meta = scene_extras(meta, mask, err)
    return LiteScene(pos, feats, offs, a.scalings, a.voxel_size, decoder, cams or None, bg, scene_meta)


def default_cameras(scene: LiteScene, n: int = 8, width: int = 256, height: int = 192) -> list[Camera]:
    """``codec.default_cameras``: the stored cameras, else an orbit around the anchors' bounds."""
    return _default_cameras(scene.cameras, scene.bounds(), n, width, height)


def image_to_uint8(image: np.ndarray) -> np.ndarray:
    """``model.image_to_uint8`` for a numpy image."""
    return (np.clip(image, 0, 1) * 255.0 + 0.5).astype(np.uint8)
