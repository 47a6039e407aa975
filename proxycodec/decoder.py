"""Neural Gaussian decoder: anchors + camera + resolution ratio xi -> explicit 3D Gaussians.

METHOD.md sections 1-2. Per anchor v seen from camera centre x_c: d = (x_v - x_c)/|x_v - x_c|, delta = |x_v - x_c|,
MLP input [f_hat_v, d, delta] (36 dims for F = 32). Three MLPs (Linear(36,32), ReLU, Linear(32,out)):
opacity (K outputs, tanh; Gaussians with opacity <= 0 are dropped), covariance (7K: per Gaussian 3 scales then a
quaternion, Scaffold-GS's layout), color (3K, sigmoid). The FiLM resolution embedding [gamma, beta] = MLP(PE(x_v, xi)),
f_hat = (1 + gamma) f + beta, starts as the identity (last layer zero).

Work follows the view: anchors whose bounding sphere misses the frustum never reach the MLPs, and the covariance and
color MLPs only run for anchors with at least one Gaussian of positive opacity.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn

from .errors import ProxycodecError
from .weights import load_state_arrays, state_arrays
from .render.project import GateConfig

EMBEDDINGS = ("film", "additive", "none")


@dataclass(frozen=True)
class DecoderConfig:
    feat_dim: int = 32
    n_offsets: int = 10
    hidden: int = 32
    embedding: str = "film"  # "film" | "additive" | "none"
    film_hidden: int = 64
    pe_pos_freqs: int = 4
    pe_res_freqs: int = 4
    scene_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scene_radius: float = 1.0
    #: The resolution band the embedding was trained on; outside it the embedding sees the nearest end of the band
    #: instead of extrapolating (measured on lego: +1.2..2.6 dB at 2.5-7.5%, +0.4..2.5 dB at 120-150%).
    film_xi_range: tuple[float, float] = (0.1, 1.0)
    gate: GateConfig = field(default_factory=GateConfig)

    def __post_init__(self) -> None:
        if self.embedding not in EMBEDDINGS:
            raise ProxycodecError(f"unknown resolution embedding {self.embedding!r}; choose from {EMBEDDINGS}")
        if not (self.scene_radius > 0 and math.isfinite(self.scene_radius)):
            raise ProxycodecError(f"scene radius must be positive, got {self.scene_radius}")
        for k in ("feat_dim", "n_offsets", "hidden", "film_hidden"):
            if int(getattr(self, k)) < 1 or int(getattr(self, k)) > 4096:
                raise ProxycodecError(f"decoder {k} = {getattr(self, k)} is out of range")
        # Frequencies beyond ~20 are meaningless in float32 (2^k pi x aliases); a hostile file must not make the
        # embedding MLP's input (and its allocation) arbitrarily wide.
        for k in ("pe_pos_freqs", "pe_res_freqs"):
            if not 0 <= int(getattr(self, k)) <= 32:
                raise ProxycodecError(f"decoder {k} = {getattr(self, k)} is out of range (0..32)")
        if len(self.scene_center) != 3 or not all(math.isfinite(float(v)) for v in self.scene_center):
            raise ProxycodecError(f"scene centre must be 3 finite numbers, got {self.scene_center!r}")
        lo, hi = (float(v) for v in self.film_xi_range) if len(self.film_xi_range) == 2 else (math.nan, math.nan)
        if not (0.025 <= lo <= hi <= 2.0):
            raise ProxycodecError(f"film_xi_range must be [lo, hi] within [0.025, 2], got {self.film_xi_range!r}")

    def to_json(self) -> dict:
        d = asdict(self)
        d["scene_center"] = list(self.scene_center)
        d["gate"] = self.gate.to_json()
        return d

    @staticmethod
    def from_json(d: dict) -> "DecoderConfig":
        try:
            if not isinstance(d, dict) or not isinstance(d.get("gate", {}), dict):
                raise ProxycodecError("bad decoder configuration: expected a JSON object (with an object 'gate')")
            d = dict(d)
            gate = GateConfig.from_json(d.pop("gate", {}))
            if not all(math.isfinite(v) for v in (gate.kappa, gate.eta)):
                raise ProxycodecError("bad decoder configuration: gate kappa and eta must be finite")
            known = {f for f in DecoderConfig.__dataclass_fields__ if f != "gate"}
            kw = {k: v for k, v in d.items() if k in known}
            for k in ("scene_center", "film_xi_range"):
                if k in kw:
                    kw[k] = tuple(float(x) for x in kw[k])
            for k in ("feat_dim", "n_offsets", "hidden", "film_hidden", "pe_pos_freqs", "pe_res_freqs"):
                if k in kw:
                    kw[k] = int(kw[k])
            return DecoderConfig(gate=gate, **kw)
        except (TypeError, ValueError) as e:
            if isinstance(e, ProxycodecError):
                raise
            raise ProxycodecError(f"bad decoder configuration: {e}") from e


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


def positional_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """NeRF-style [x, sin(2^k pi x), cos(2^k pi x)] for k < n_freqs."""
    if n_freqs == 0:
        return x
    freqs = (2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)) * math.pi
    xf = x[..., None] * freqs  # [..., D, L]
    return torch.cat([x, torch.sin(xf).flatten(-2), torch.cos(xf).flatten(-2)], -1)


def _mlp(n_in: int, hidden: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, n_out))


class GaussianDecoder(nn.Module):
    """Opacity / covariance / color MLPs and the resolution embedding. Holds weights only (no anchors)."""

    def __init__(self, config: DecoderConfig = DecoderConfig()):
        super().__init__()
        self.config = config
        F, K, h = config.feat_dim, config.n_offsets, config.hidden
        n_in = F + 4
        self.mlp_opacity = _mlp(n_in, h, K)
        self.mlp_cov = _mlp(n_in, h, 7 * K)
        self.mlp_color = _mlp(n_in, h, 3 * K)
        if config.embedding != "none":
            n_pe = 3 * (1 + 2 * config.pe_pos_freqs) + (1 + 2 * config.pe_res_freqs)
            n_out = 2 * F if config.embedding == "film" else F
            self.mlp_embed = _mlp(n_pe, config.film_hidden, n_out)
            nn.init.zeros_(self.mlp_embed[2].weight)
            nn.init.zeros_(self.mlp_embed[2].bias)

    # -------------------------------------------------------------- resolution embedding
    def embed(self, positions: torch.Tensor, features: torch.Tensor, xi: float) -> torch.Tensor:
        """f_hat = (1 + gamma) f + beta (FiLM), f + beta (additive) or f (none)."""
        cfg = self.config
        if cfg.embedding == "none" or features.shape[0] == 0:
            return features
        c = torch.as_tensor(cfg.scene_center, dtype=positions.dtype, device=positions.device)
        xn = ((positions - c) / cfg.scene_radius).clamp(-4.0, 4.0)
        lo, hi = cfg.film_xi_range
        s = torch.full_like(positions[:, :1], math.log2(min(max(float(xi), lo), hi)) / 4.0)
        pe = torch.cat([positional_encoding(xn, cfg.pe_pos_freqs), positional_encoding(s, cfg.pe_res_freqs)], -1)
        out = self.mlp_embed(pe)
        if cfg.embedding == "additive":
            return features + out
        gamma, beta = out.split(cfg.feat_dim, dim=-1)
        return (1.0 + gamma) * features + beta

    # -------------------------------------------------------------- anchors -> Gaussians
    def forward(
        self,
        positions: torch.Tensor,  # [M, 3]
        features: torch.Tensor,  # [M, F]
        offsets: torch.Tensor,  # [M, K, 3]
        scalings: torch.Tensor,  # [M, 6] log
        camera_center: torch.Tensor,  # [3]
        xi: float,
    ) -> NeuralGaussians:
        K = self.config.n_offsets
        f_hat = self.embed(positions, features, xi)
        view = positions - camera_center
        dist = view.norm(dim=1, keepdim=True)
        x = torch.cat([f_hat, view / dist.clamp_min(1e-12), dist], -1)

        opacity = torch.tanh(self.mlp_opacity(x))  # [M, K]
        with torch.no_grad():
            mask = opacity > 0
            live = mask.any(1).nonzero().squeeze(1)
        # Covariance and color only for anchors with at least one surviving Gaussian.
        x, opacity, mask = x[live], opacity[live], mask[live]
        cov = self.mlp_cov(x).reshape(-1, K, 7)
        color = torch.sigmoid(self.mlp_color(x)).reshape(-1, K, 3)
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


def visible_anchors(positions: torch.Tensor, radius: torch.Tensor, camera, near: float = 0.01) -> torch.Tensor:
    """Indices of anchors whose bounding sphere intersects the view frustum (exact sphere-vs-plane test)."""
    with torch.no_grad():
        R, t, _ = camera.torch_params(positions.device, positions.dtype)
        p = positions @ R.T + t
        W, H, fx, fy, cx, cy = camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy
        planes = torch.tensor(  # inward normals of the four side planes through the camera centre
            [[fx, 0.0, cx], [-fx, 0.0, W - cx], [0.0, fy, cy], [0.0, -fy, H - cy]], dtype=p.dtype, device=p.device
        )
        planes = planes / planes.norm(dim=1, keepdim=True)
        inside = (p @ planes.T >= -radius[:, None]).all(1) & (p[:, 2] + radius > near)
        return inside.nonzero().squeeze(1)
