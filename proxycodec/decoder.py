"""Neural Gaussian decoder: anchors + camera + resolution ratio xi -> explicit 3D Gaussians.

METHOD.md sections 1-2. Per anchor v seen from camera centre x_c: d = (x_v - x_c)/|x_v - x_c|, delta = |x_v - x_c|,
MLP input [f_hat_v, d, delta] (36 dims for F = 32). Three MLPs (Linear(36,32), ReLU, Linear(32,out)):
opacity (K outputs, tanh; Gaussians with opacity <= 0 are dropped), covariance (7K: per Gaussian 3 scales then a
quaternion, Scaffold-GS's layout), color (3K, sigmoid). The FiLM resolution embedding [gamma, beta] = MLP(PE(x_v, xi)),
f_hat = (1 + gamma) f + beta, starts as the identity (last layer zero).

Work follows the view: anchors whose bounding sphere misses the frustum never reach the MLPs, and the covariance and
color MLPs only run for anchors with at least one Gaussian of positive opacity.

An imported Scaffold-GS output (``scaffold_gs.py``) may use Scaffold-GS's variants, recorded in ``DecoderConfig``:
MLPs without the distance input ([f_hat, d], F + 3 inputs; ``opacity_dist``/``cov_dist``/``color_dist``) and its
feature bank (``feature_bank``: f_hat is blended with its stride-4 and stride-2 channels by softmax(MLP([d, delta])),
after the FiLM embedding). The defaults are the decoder above.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from .devices import upload
from .netconfig import DecoderConfig  # defined torch-free (proxycodec.lite reads it too)
from .weights import load_state_arrays, state_arrays


@dataclass
class NeuralGaussians:
    means: torch.Tensor  # [N, 3] relative to ``origin`` (world axes)
    quats: torch.Tensor  # [N, 4]
    scales: torch.Tensor  # [N, 3]
    opacities: torch.Tensor  # [N] in (0, 1]
    colors: torch.Tensor  # [N, 3]
    anchor_index: torch.Tensor  # [N] index into the anchors given to the decoder
    slot: torch.Tensor  # [N] which of the K offsets
    origin: torch.Tensor  # [3] world point the means are relative to (the camera centre)

    @property
    def count(self) -> int:
        return int(self.means.shape[0])

    def world_means(self) -> torch.Tensor:
        return self.means + self.origin


@functools.lru_cache(maxsize=64)
def _frequencies(n_freqs: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """2^k pi for k < n_freqs, made once per device and dtype (three kernel launches a call on a GPU otherwise); a
    normal tensor even when first asked for under ``torch.inference_mode`` (autograd may save it later)."""
    with torch.inference_mode(False), torch.no_grad():
        return (2.0 ** torch.arange(n_freqs, device=device, dtype=dtype)) * math.pi


def positional_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """NeRF-style [x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs."""
    if n_freqs == 0:
        return x
    xf = x[..., None] * _frequencies(n_freqs, x.device, x.dtype)  # [..., D, L]
    return torch.cat([x, torch.sin(xf).flatten(-2), torch.cos(xf).flatten(-2)], -1)


def _mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, n_out))


class GaussianDecoder(nn.Module):
    """Opacity / covariance / color MLPs and the resolution embedding. Holds weights only (no anchors)."""

    def __init__(self, config: DecoderConfig = DecoderConfig()):
        super().__init__()
        self.config = config
        F, K, h = config.feat_dim, config.n_offsets, config.hidden
        n_in = config.mlp_inputs()  # F + 4, or F + 3 for a Scaffold-GS MLP without the distance
        self.mlp_opacity = _mlp(n_in["mlp_opacity"], h, K)
        self.mlp_cov = _mlp(n_in["mlp_cov"], h, 7 * K)
        self.mlp_color = _mlp(n_in["mlp_color"], h, 3 * K)
        if config.embedding != "none":
            n_pe = 3 * (1 + 2 * config.pe_pos_freqs) + (1 + 2 * config.pe_res_freqs)
            n_out = 2 * F if config.embedding == "film" else F
            self.mlp_embed = _mlp(n_pe, config.film_hidden, n_out)
            nn.init.zeros_(self.mlp_embed[2].weight)
            nn.init.zeros_(self.mlp_embed[2].bias)
        if config.feature_bank:  # Scaffold-GS's use_feat_bank: [d, delta] -> 3 blend weights (softmax)
            self.mlp_feature_bank = _mlp(4, config.feature_bank, 3)

    # -------------------------------------------------------------- resolution embedding
    def embed(self, positions: torch.Tensor, features: torch.Tensor, xi: float) -> torch.Tensor:
        """f_hat = (1 + gamma) f + beta (FiLM), f + beta (additive) or f (none)."""
        cfg = self.config
        if cfg.embedding == "none" or features.shape[0] == 0:
            return features
        c = upload(cfg.scene_center, positions.device, positions.dtype)
        xn = ((positions - c) / cfg.scene_radius).clamp(-4.0, 4.0)
        lo, hi = cfg.film_xi_range
        s = torch.full_like(positions[:, :1], math.log2(min(max(float(xi), lo), hi)) / 4.0)
        pe = torch.cat([positional_encoding(xn, cfg.pe_pos_freqs), positional_encoding(s, cfg.pe_res_freqs)], -1)
        out = self.mlp_embed(pe)
        if cfg.embedding == "additive":
            return features + out
        gamma, beta = out.split(cfg.feat_dim, dim=-1)
        return (1.0 + gamma) * features + beta

    def feature_bank(self, features: torch.Tensor, direction: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
        """Scaffold-GS's feature bank (``use_feat_bank``): w = softmax(MLP([d, delta])), f' = w0 tile(f[::4], 4) +
        w1 tile(f[::2], 2) + w2 f, in its order of operations."""
        w = torch.softmax(self.mlp_feature_bank(torch.cat([direction, dist], -1)), dim=1)  # [M, 3]
        return (features[:, ::4].repeat(1, 4) * w[:, :1] + features[:, ::2].repeat(1, 2) * w[:, 1:2]
                + features * w[:, 2:])

    # -------------------------------------------------------------- anchors -> Gaussians
    def mlp_input(self, positions: torch.Tensor, features: torch.Tensor, camera_center: torch.Tensor, xi: float
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """-> (anchor - camera [M, 3], the MLPs' input [M, F + 4]: embedded feature, view direction, distance in
        the MLPs' units). Each MLP reads it whole or without the distance (``mlp_inputs``). ``camera_center``: [3],
        or [M, 3], a camera per anchor (``train.fit_initial_colors``)."""
        cfg = self.config
        f_hat = self.embed(positions, features, xi)
        view = positions - camera_center
        dist = view.norm(dim=1, keepdim=True)
        direction = view / dist.clamp_min(1e-12)
        dist = dist / cfg.length_unit  # the MLPs' units (exact for 1)
        if cfg.feature_bank:
            f_hat = self.feature_bank(f_hat, direction, dist)
        return view, torch.cat([f_hat, direction, dist], -1)

    def forward(
        self,
        positions: torch.Tensor,  # [M, 3]
        features: torch.Tensor,  # [M, F]
        offsets: torch.Tensor,  # [M, K, 3]
        scalings: torch.Tensor,  # [M, 6] log
        camera_center: torch.Tensor,  # [3]
        xi: float,
    ) -> NeuralGaussians:
        cfg = self.config
        K = cfg.n_offsets
        view, x = self.mlp_input(positions, features, camera_center, xi)
        opacity = torch.tanh(self.mlp_opacity(x if cfg.opacity_dist else x[:, :-1]))  # [M, K]
        with torch.no_grad():
            mask = opacity > 0
            live = mask.any(1).nonzero().squeeze(1)
        # Covariance and color only for anchors with at least one surviving Gaussian.
        x, opacity, mask = x[live], opacity[live], mask[live]
        cov = self.mlp_cov(x if cfg.cov_dist else x[:, :-1]).reshape(-1, K, 7)
        color = torch.sigmoid(self.mlp_color(x if cfg.color_dist else x[:, :-1])).reshape(-1, K, 3)
        sc = torch.exp(scalings[live])  # [m, 6]
        scales = sc[:, None, 3:] * torch.sigmoid(cov[..., :3])
        # Centres relative to the camera (float32 keeps its precision far from the world origin).
        means = view[live][:, None, :] + offsets[live] * sc[:, None, :3]
        a_idx, slot = mask.nonzero(as_tuple=True)
        return NeuralGaussians(
            means=means[a_idx, slot], quats=cov[a_idx, slot, 3:], scales=scales[a_idx, slot],
            opacities=opacity[a_idx, slot], colors=color[a_idx, slot], anchor_index=live[a_idx], slot=slot,
            origin=camera_center.detach(),
        )

    # -------------------------------------------------------------- persistence (raw arrays + JSON, no pickle)
    def state_arrays(self) -> dict[str, np.ndarray]:
        return state_arrays(self)

    @classmethod
    def from_arrays(cls, config: DecoderConfig, arrays: dict[str, np.ndarray]) -> "GaussianDecoder":
        return load_state_arrays(cls(config), arrays, "decoder")  # type: ignore[return-value]


@torch.no_grad()
def live_slots(
    decoder: GaussianDecoder,
    positions: torch.Tensor,  # [M, 3]
    features: torch.Tensor,  # [M, F] as the renderer will see them (leaves predicted)
    viewpoints: torch.Tensor,  # [V, 3] camera centres
    xis: Sequence[float],
    threshold: float = 0.0,
    chunk: int = 64,
) -> torch.Tensor:
    """[M, K] bool: whether a neural Gaussian's opacity exceeds ``threshold`` from any viewpoint at any xi.

    The opacity MLP sees the embedded feature (which depends on xi only), the unit view direction and the
    distance; the first layer is split so that only its 4 (3 without distance) view columns are recomputed per
    viewpoint. With a feature bank the feature itself depends on the view and is recomputed too.
    """
    cfg = decoder.config
    M, K = positions.shape[0], cfg.n_offsets
    live = torch.zeros(M, K, dtype=torch.bool, device=positions.device)
    if M == 0 or viewpoints.shape[0] == 0:
        return live
    lin1, lin2 = decoder.mlp_opacity[0], decoder.mlp_opacity[2]
    F = features.shape[1]
    n_view = 4 if cfg.opacity_dist else 3  # direction (+ distance)
    w_f, w_v = lin1.weight[:, :F], lin1.weight[:, F:F + n_view]  # [h, F], [h, 4 or 3]
    pos = positions.to(lin1.weight.dtype)
    if cfg.feature_bank:  # features per (viewpoint, anchor): fewer viewpoints at a time
        chunk = max(1, min(chunk, (1 << 20) // M))
    for xi in xis:
        f_hat = decoder.embed(pos, features.to(pos.dtype), float(xi))
        base = f_hat @ w_f.T + lin1.bias  # [M, h]
        for v0 in range(0, viewpoints.shape[0], chunk):
            vp = viewpoints[v0:v0 + chunk].to(pos.dtype)  # [c, 3]
            view = pos[None] - vp[:, None]  # [c, M, 3]
            dist = view.norm(dim=-1, keepdim=True)
            d = torch.cat([view / dist.clamp_min(1e-12), dist], -1)  # [c, M, 4]
            x = d[..., :n_view] @ w_v.T  # [c, M, h]
            if cfg.feature_bank:  # the feature itself depends on the view: no shared base
                c = d.shape[0]
                fb = decoder.feature_bank(f_hat.repeat(c, 1), d[..., :3].reshape(-1, 3), d[..., 3:].reshape(-1, 1))
                x = x + (fb @ w_f.T).reshape(c, M, -1) + lin1.bias
            else:
                x = base[None] + x
            o = torch.tanh(torch.relu(x) @ lin2.weight.T + lin2.bias)  # [c, M, K]
            live |= (o > threshold).any(0)
    return live


def visible_anchors(positions: torch.Tensor, radius: torch.Tensor, camera, near: float = 0.01) -> torch.Tensor:
    """Indices of anchors whose bounding sphere intersects the view frustum (exact sphere-vs-plane test)."""
    with torch.no_grad():
        R, t, _ = camera.torch_params(positions.device, positions.dtype)
        p = positions @ R.T + t
        W, H, fx, fy, cx, cy = camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
        planes = upload(  # inward normals of the four side planes through the camera centre
            [[fx, 0.0, cx], [-fx, 0.0, W - cx], [0.0, fy, cy], [0.0, -fy, H - cy]], p.device, p.dtype)
        planes = planes / planes.norm(dim=1, keepdim=True)
        inside = (p @ planes.T >= -radius[:, None]).all(1) & (p[:, 2] + radius > near)
        return inside.nonzero().squeeze(1)
