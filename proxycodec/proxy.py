"""Proxy anchors and the residual anchor predictor (METHOD.md section 3).

- ``select_proxies``: density-aware selection (supplement 7.3, eq. 15-16). Cell index g_i = floor(v_i / eps); in every
  occupied cell ceil(rho * |G_l|) anchors are drawn uniformly at random (the paper's), or, with ``method="spread"``,
  picked by a greedy k-median within the cell (ours: leaves closer to their proxies). Deterministic for a seed and
  independent of the order the anchors come in (each anchor's random key is drawn in lexicographic position order).
- ``nearest_proxy``: for every anchor, the index of its nearest proxy (a proxy maps to itself). Ties are broken
  explicitly (smallest squared distance, then the predictor configuration's rule: the smaller position, or for
  files written before that rule, the smaller index) so trainer, encoder and decoder always agree.
- ``ResidualPredictor``: [f_k (F), PE(log distance), PE(unit direction proxy->leaf)] -> encoder -> residual MLP blocks
  -> delta (F, plus 3K offset deltas when it also predicts offsets). Prediction = proxy value + delta. The head starts
  at zero, so an untrained predictor is exactly the proxy-copy baseline.
- ``recon_loss``: L_recon = mean_i ||f~_i - f_i||^2 + 0.1 (1 - cos(f~_i, f_i)); ablation variants ``mse`` and ``l1``
  (supplement Table 6).
- ``ProxyLeafMLP``: the supplement's "Proxy&Leaf (MLP)" baseline (Table 5), for the ablation only (fit / eval; the
  container stores residual predictors only).
- ``train_predictor``: Adam on L_recon over 20% of the leaves drawn per iteration (stage-2's feature-only part).
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .devices import module_device, upload
from .decoder import positional_encoding
from . import nearest as _nearest
from .errors import ProxycodecError
from .formats.container import read_container
from .netconfig import PredictorConfig
from .optim import Adam
from .weights import load_state_arrays, state_arrays

__all__ = [
    "default_cell_size", "select_proxies", "nearest_proxy", "nearest_proxies", "nearest_column", "PredictorConfig",
    "ResidualPredictor", "predictor_inputs", "predictor_geometry", "proxy_encodings", "recon_loss",
    "offset_recon_loss", "TrainConfig", "TrainResult", "train_predictor", "proxies_per_cell", "PROXY_SELECTIONS",
    "check_proxy_selection", "RECON_LOSSES",
    "PREDICTOR_KINDS", "predictor_neighbours", "ProxyLeafConfig", "ProxyLeafMLP", "predictor_from_json",
    "load_fitted_predictor",
]


# ---------------------------------------------------------------------------------------------- proxy selection
def _cells(positions: np.ndarray, cell_size: float) -> np.ndarray:
    """[M] cell id (dense, 0..n_cells-1) of g_i = floor(v_i / eps), computed in float64."""
    g = np.floor(np.asarray(positions, dtype=np.float64) / float(cell_size)).astype(np.int64)
    _, inv = np.unique(g, axis=0, return_inverse=True)
    return inv.reshape(-1)


def proxies_per_cell(counts: np.ndarray, ratio: float) -> np.ndarray:
    """ceil(rho * n) per cell, guarded against float error (0.3 * 10 must give 3, not 4)."""
    return np.ceil(np.asarray(counts, dtype=np.float64) * float(ratio) - 1e-9).astype(np.int64)


def default_cell_size(positions, voxel_size: float, target: float = 10.0, max_multiple: int = 1024) -> float:
    """A multiple m of the voxel size such that an occupied cell holds ~``target`` anchors on average.

    The mean occupancy grows with m; the m whose mean is closest to ``target`` (in log ratio) wins.
    """
    p = np.asarray(positions.detach().cpu() if isinstance(positions, torch.Tensor) else positions, dtype=np.float64)
    if len(p) == 0:
        return float(voxel_size)
    best, best_err, m = 1, math.inf, 1
    while m <= max_multiple:
        n_cells = int(_cells(p, m * voxel_size).max()) + 1
        mean = len(p) / n_cells
        err = abs(math.log(mean / target))
        if err < best_err:
            best, best_err = m, err
        if mean >= target or n_cells == 1:
            break
        m += 1 if m < 8 else max(1, m // 4)
    return float(best * voxel_size)


#: Proxy selection methods: "random" is the paper's ([S 7.3]: ceil(rho |G_l|) uniformly at random per cell);
#: "spread" picks the same number per cell, greedily minimising the sum of each anchor's distance to its nearest
#: proxy in the cell (a greedy k-median), so that leaves sit closer to the proxy they are predicted from.
PROXY_SELECTIONS = ("random", "spread")
#: Cells with more anchors than this fall back to random selection under "spread" (its cost is O(n^2) per cell).
SPREAD_MAX_CELL = 512


def check_proxy_selection(method: str) -> None:
    """Refuses a proxy selection method other than ``PROXY_SELECTIONS`` (``select_proxies`` and the fit / encode
    configurations, which check it before any work)."""
    if method not in PROXY_SELECTIONS:
        raise ProxycodecError(f"unknown proxy selection {method!r}; choose from {', '.join(PROXY_SELECTIONS)}")


def select_proxies(positions, cell_size: float, ratio: float = 0.3, seed: int = 0,
                   method: str = "random") -> np.ndarray:
    """[M] bool mask of proxy anchors: ceil(ratio * |G_l|) in every occupied cell, drawn uniformly at random
    (``method="random"``, the paper's) or spread out over the cell (``"spread"``, a greedy k-median; ``seed`` then
    only matters for cells above ``SPREAD_MAX_CELL`` anchors). Both are independent of the order of the anchors."""
    p = np.asarray(positions.detach().cpu() if isinstance(positions, torch.Tensor) else positions, dtype=np.float64)
    if not (0.0 < ratio <= 1.0):
        raise ProxycodecError(f"proxy ratio must be in (0, 1], got {ratio}")
    if not (math.isfinite(cell_size) and cell_size > 0):
        raise ProxycodecError(f"cell size must be positive, got {cell_size}")
    check_proxy_selection(method)
    M = len(p)
    if M == 0:
        return np.zeros(0, dtype=bool)
    cell = _cells(p, cell_size)
    # Random keys drawn in lexicographic position order: the selection does not depend on the input order.
    canon = np.lexsort((p[:, 2], p[:, 1], p[:, 0]))
    key = np.empty(M)
    key[canon] = np.random.default_rng(seed).random(M)
    counts = np.bincount(cell)
    quota = proxies_per_cell(counts, ratio)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])  # first position of each cell in cell order
    if method == "spread":
        key = np.where(counts[cell] > SPREAD_MAX_CELL, key, _spread_keys(p, cell, counts, starts, quota, canon))
    order = np.lexsort((key, cell))  # by cell, smallest keys first
    rank = np.arange(M) - starts[cell[order]]
    mask = np.zeros(M, dtype=bool)
    mask[order] = rank < quota[cell[order]]
    return mask


def _spread_keys(p: np.ndarray, cell: np.ndarray, counts: np.ndarray, starts: np.ndarray, quota: np.ndarray,
                 canon: np.ndarray) -> np.ndarray:
    """[M] keys in [0, 1): the greedy k-median's picks of every cell (up to ``SPREAD_MAX_CELL`` anchors) get keys
    below 0.5 in pick order, the rest 0.5 and up. Cells of the same size are processed together: [C, n, n] distances,
    then ``quota`` greedy steps, each adding the anchor that most lowers the sum of distances to the nearest pick.
    Within a cell anchors are taken in lexicographic position order (``canon``), so ties (argmin: first) do not
    depend on the input order."""
    keys = np.full(len(p), 0.75)
    order = canon[np.argsort(cell[canon], kind="stable")]  # by cell, canonical position order within
    for n in np.unique(counts):
        if n > SPREAD_MAX_CELL:
            continue
        all_cells = np.nonzero(counts == n)[0]
        k = int(quota[all_cells[0]])
        chunk = max(1, (1 << 21) // (n * n))  # bounds the [C, n, n] distance block to ~16 MB
        for c0 in range(0, len(all_cells), chunk):
            cells = all_cells[c0:c0 + chunk]
            idx = order[starts[cells][:, None] + np.arange(n)[None, :]]  # [C, n] anchor indices
            q = p[idx]  # [C, n, 3]
            D = np.sqrt(((q[:, :, None, :] - q[:, None, :, :]) ** 2).sum(-1))  # [C, n, n]
            cur = np.full((len(cells), n), np.inf)
            picked = np.zeros((len(cells), n), dtype=bool)
            rows = np.arange(len(cells))
            for step in range(k):
                cost = np.minimum(cur[:, None, :], D).sum(-1)  # [C, n]: total distance if candidate j were added
                cost[picked] = np.inf
                j = np.argmin(cost, axis=1)
                picked[rows, j] = True
                cur = np.minimum(cur, D[rows, j])
                keys[idx[rows, j]] = 0.5 * step / k
    return keys


#: Below this many (leaf, proxy) pairs the nearest proxy is found by exhaustive search, above it by a kd-tree
#: (``nearest.py``). Read at call time, so tests can lower it here.
BRUTE_FORCE_PAIRS = _nearest.BRUTE_FORCE_PAIRS


def nearest_proxies(positions, proxy_mask, k: int = 1, ties: str = "position", unit: float | None = None
                    ) -> np.ndarray:
    """[M, k] int64: each anchor's ``k`` nearest proxies, nearest first (``nearest.nearest_proxies``; ``ties``: a
    predictor configuration's rule; ``unit``: its lattice unit under "grid")."""
    p = positions.detach().cpu().numpy() if isinstance(positions, torch.Tensor) else positions
    return _nearest.nearest_proxies(p, proxy_mask, k, ties, unit=unit, brute_force_pairs=BRUTE_FORCE_PAIRS)


def predictor_neighbours(positions, proxy_mask, config) -> np.ndarray:
    """[M, context] the proxies a predictor of ``config`` sees per anchor, under its tie rule
    (``nearest.predictor_neighbours``; ``positions``: an array or a tensor)."""
    p = positions.detach().cpu().numpy() if isinstance(positions, torch.Tensor) else positions
    return _nearest.predictor_neighbours(p, proxy_mask, config, brute_force_pairs=BRUTE_FORCE_PAIRS)


def nearest_proxy(positions, proxy_mask, ties: str = "position", unit: float | None = None) -> np.ndarray:
    """[M] int64: index (into ``positions``, an array or a tensor) of each anchor's nearest proxy; proxies map to
    themselves. Ties go to the first proxy in ``ties`` order (``nearest.nearest_proxy`` has the details)."""
    p = positions.detach().cpu().numpy() if isinstance(positions, torch.Tensor) else positions
    return _nearest.nearest_proxy(p, proxy_mask, ties, unit=unit, brute_force_pairs=BRUTE_FORCE_PAIRS)


# ---------------------------------------------------------------------------------------------- predictor
class _Block(nn.Module):
    def __init__(self, h: int):
        super().__init__()
        self.fc1 = nn.Linear(h, h)
        self.fc2 = nn.Linear(h, h)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.fc2(torch.relu(self.fc1(x)))


def predictor_inputs(positions: torch.Tensor, proxy_pos: torch.Tensor, dist_ref: float,
                     pe_dist_freqs: int, pe_dir_freqs: int) -> torch.Tensor:
    """[L, 1 + 2 Ld + 3 (1 + 2 Lr)]: PE of log distance and of the unit direction proxy -> leaf."""
    v = positions - proxy_pos  # [L, 3]
    d = v.norm(dim=1, keepdim=True)
    u = v / d.clamp_min(1e-12)
    s = torch.log(d.clamp_min(1e-6 * dist_ref) / dist_ref) / 4.0
    return torch.cat([positional_encoding(s, pe_dist_freqs), positional_encoding(u, pe_dir_freqs)], -1)


def nearest_column(nearest: torch.Tensor) -> torch.Tensor:
    """[M]: each anchor's nearest proxy, from ``nearest`` given as [M] (``nearest_proxy``) or [M, k]
    (``nearest_proxies``, nearest first)."""
    return nearest[:, 0] if nearest.dim() == 2 else nearest


def gather_rows(t: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``t[index]`` along dim 0, with a deterministic backward. Many leaves share a proxy, so ``index`` repeats
    rows: the backward of advanced indexing (``index_put_`` with accumulate) adds the repeats with parallel atomic
    adds on CPU, in an order that changes from run to run (torch 2.13: fits diverged from the first stage-2
    iteration); ``index_select``'s backward (``index_add_``) adds them in index order."""
    return t.index_select(0, index)


def offset_recon_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The offsets' reconstruction term: squared error summed over a leaf's K x 3 offsets, mean over leaves."""
    return ((pred - target) ** 2).sum((1, 2)).mean()


def _context_columns(near: torch.Tensor, cfg: PredictorConfig) -> torch.Tensor:
    """``near`` as [M, >= context] (an [M] nearest-proxy column is [M, 1]), checked against ``cfg.context``."""
    if near.dim() == 1:
        near = near[:, None]
    if near.shape[1] < cfg.context:
        raise ProxycodecError(f"the predictor sees {cfg.context} proxies per leaf; got {near.shape[1]}")
    return near


def _encode_from_proxies(positions: torch.Tensor, k: torch.Tensor, p: torch.Tensor, cfg: PredictorConfig
                         ) -> list[torch.Tensor]:
    """Per proxy j < ``cfg.context`` (``k`` [R, >= context], nearest first): ``predictor_inputs`` of the vector from
    ``positions[k[:, j]]`` to ``p`` [R, 3]."""
    return [predictor_inputs(p, positions[k[:, j]], cfg.dist_ref, cfg.pe_dist_freqs, cfg.pe_dir_freqs)
            for j in range(cfg.context)]


def proxy_encodings(positions: torch.Tensor, near: torch.Tensor, cfg: PredictorConfig,
                    rows: torch.Tensor | None = None) -> torch.Tensor:
    """[R, context, n_geo], without gradient: for the anchors ``rows`` (default all), the encoding of the vector from
    each of their ``cfg.context`` proxies (``near``, nearest first) to them. It depends on positions and neighbours
    alone, so the trainer's stage 2, where both are fixed, computes it once (``predictor_geometry``'s
    ``encodings``) instead of ~10 operations per proxy and call."""
    near = _context_columns(near, cfg)
    with torch.no_grad():
        k = near if rows is None else near[rows]
        p = positions if rows is None else positions[rows]
        return torch.stack(_encode_from_proxies(positions, k, p, cfg), 1)


def predictor_geometry(positions: torch.Tensor, features: torch.Tensor, near: torch.Tensor, leaves: torch.Tensor,
                       cfg: PredictorConfig, encodings: torch.Tensor | None = None) -> torch.Tensor:
    """Everything the predictor sees besides the nearest proxy's feature, for the anchors ``leaves``: the encoding
    of the nearest proxy -> leaf vector; with ``cfg.context`` > 1, per further proxy j (``near`` [M, context],
    nearest first) its feature minus the nearest's and the encoding of its own vector to the leaf. ``encodings``:
    ``proxy_encodings`` of every anchor, when the caller holds it (rows taken from it; else computed)."""
    near = _context_columns(near, cfg)
    k = near[leaves]
    enc = (_encode_from_proxies(positions, k, positions[leaves], cfg) if encodings is None
           else encodings[leaves].unbind(1))
    parts = [enc[0]]
    f0 = gather_rows(features, k[:, 0]) if cfg.context > 1 else None
    for j in range(1, cfg.context):
        parts += [gather_rows(features, k[:, j]) - f0, enc[j]]
    return torch.cat(parts, -1) if len(parts) > 1 else parts[0]


class ResidualPredictor(nn.Module):
    """f~_q = f_k + delta_f(f_k, PE(log |v_q - v_k|), PE(unit(v_q - v_k))) (and offsets likewise, optionally)."""

    def __init__(self, config: PredictorConfig = PredictorConfig()):
        super().__init__()
        self.config = config
        h = config.hidden
        self.encoder = nn.Sequential(nn.Linear(config.n_in, h), nn.ReLU())
        self.blocks = nn.ModuleList(_Block(h) for _ in range(config.n_blocks))
        self.head = nn.Linear(h, config.n_out)
        nn.init.zeros_(self.head.weight)  # starts as the proxy-copy baseline
        nn.init.zeros_(self.head.bias)

    def forward(
        self,
        proxy_features: torch.Tensor,  # [L, F] features of each leaf's nearest proxy
        geometry: torch.Tensor,  # [L, G] predictor_inputs(...)
        proxy_offsets: torch.Tensor | None = None,  # [L, K, 3] when predict_offsets
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        cfg = self.config
        x = self.encoder(torch.cat([proxy_features, geometry], -1))
        for b in self.blocks:
            x = b(x)
        out = self.head(x)
        feats = proxy_features + out[:, :cfg.feat_dim]
        offs = None
        if cfg.predict_offsets:
            if proxy_offsets is None:
                raise ProxycodecError("this predictor also predicts offsets: pass the proxies' offsets")
            offs = proxy_offsets + out[:, cfg.feat_dim:].reshape(-1, cfg.n_offsets, 3)
        return feats, offs

    def predict(self, positions: torch.Tensor, features: torch.Tensor, nearest: torch.Tensor,
                leaves: torch.Tensor, offsets: torch.Tensor | None = None, encodings: torch.Tensor | None = None):
        """Predictions for the anchors ``leaves`` given every anchor's position, the proxies' features/offsets
        (rows of leaves are ignored) and ``nearest`` (``nearest_proxy``); ``encodings``: ``proxy_encodings`` of
        every anchor, where the caller keeps it."""
        cfg = self.config
        geo = predictor_geometry(positions, features, nearest, leaves, cfg, encodings)
        k = nearest_column(nearest)[leaves]
        return self(gather_rows(features, k), geo,
                    gather_rows(offsets, k) if (offsets is not None and cfg.predict_offsets) else None)

    # ------------------------------------------------------------------ persistence (raw arrays, no pickle)
    def state_arrays(self) -> dict[str, np.ndarray]:
        return state_arrays(self)

    @classmethod
    def from_arrays(cls, config: PredictorConfig, arrays: dict[str, np.ndarray]) -> "ResidualPredictor":
        return load_state_arrays(cls(config), arrays, "predictor")  # type: ignore[return-value]


#: L_recon variants (supplement Table 6): ours, and the single-objective ablations.
RECON_LOSSES = ("mse+cos", "mse", "l1")


def recon_loss(pred: torch.Tensor, target: torch.Tensor, cos_weight: float = 0.1,
               kind: str = "mse+cos") -> torch.Tensor:
    """L_recon = mean_i ||pred_i - target_i||^2 + cos_weight * mean_i (1 - cos(pred_i, target_i)).

    The squared error is summed over channels and averaged over rows, as METHOD.md section 3 writes it.
    ``kind`` selects the ablation variants of supplement Table 6 (each "a single objective"): ``mse`` =
    mean_i ||pred_i - target_i||^2, ``l1`` = mean_i ||pred_i - target_i||_1 (summed over channels as well).
    """
    if kind not in RECON_LOSSES:
        raise ProxycodecError(f"unknown reconstruction loss {kind!r}; choose from {', '.join(RECON_LOSSES)}")
    if pred.shape != target.shape or pred.ndim != 2:
        raise ProxycodecError(f"recon_loss expects two [N, F] tensors, got {tuple(pred.shape)} and "
                              f"{tuple(target.shape)}")
    if pred.shape[0] == 0:
        return pred.sum() * 0.0
    if kind == "l1":
        return (pred - target).abs().sum(1).mean()
    mse = ((pred - target) ** 2).sum(1).mean()
    if kind == "mse":
        return mse
    cos = F.cosine_similarity(pred, target, dim=1, eps=1e-8)
    return mse + cos_weight * (1.0 - cos).mean()


# ---------------------------------------------------------------------------------------------- Proxy&Leaf MLP
#: Leaf-feature predictors: ours, and the supplement's Proxy&Leaf (MLP) baseline (Table 5).
PREDICTOR_KINDS = ("residual", "proxy-leaf-mlp")


@dataclass(frozen=True)
class ProxyLeafConfig:
    """Configuration of :class:`ProxyLeafMLP` (JSON carries ``kind`` so a reader can tell it from a residual one)."""

    feat_dim: int = 32
    n_offsets: int = 10
    hidden: int = 64
    n_blocks: int = 2
    pe_pos_freqs: int = 8  # finest period ~1.7 voxels at voxel = extent / 128
    scene_center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scene_radius: float = 1.0
    kind: str = "proxy-leaf-mlp"
    predict_offsets: bool = False  # never: the ablation concerns features only
    ties: str = "position"  # equidistant proxies (``PredictorConfig.ties``)

    def __post_init__(self) -> None:
        for k in ("feat_dim", "n_offsets", "hidden"):
            if not 1 <= int(getattr(self, k)) <= 4096:
                raise ProxycodecError(f"predictor {k} = {getattr(self, k)} is out of range")
        for k in ("n_blocks", "pe_pos_freqs"):
            if not 0 <= int(getattr(self, k)) <= 64:
                raise ProxycodecError(f"predictor {k} = {getattr(self, k)} is out of range")
        if self.kind != "proxy-leaf-mlp" or self.predict_offsets:
            raise ProxycodecError("a Proxy&Leaf MLP predicts features only")
        if self.ties not in ("index", "position"):  # no length unit for "grid"
            raise ProxycodecError(f"predictor ties = {self.ties!r}: must be 'index' or 'position'")
        if not (math.isfinite(self.scene_radius) and self.scene_radius > 0):
            raise ProxycodecError(f"predictor scene_radius must be positive, got {self.scene_radius}")

    @property
    def n_token(self) -> int:
        return self.feat_dim + 3 * (1 + 2 * self.pe_pos_freqs)

    def to_json(self) -> dict:
        d = asdict(self)
        d["scene_center"] = [float(v) for v in self.scene_center]
        return d

    @staticmethod
    def from_json(d: dict) -> "ProxyLeafConfig":
        try:
            kw = {k: d[k] for k in ProxyLeafConfig.__dataclass_fields__ if k in d}
            if "scene_center" in kw:
                kw["scene_center"] = tuple(float(v) for v in kw["scene_center"])
            kw.setdefault("ties", "index")  # written before the field existed
            return ProxyLeafConfig(**kw)
        except (TypeError, ValueError) as e:
            if isinstance(e, ProxycodecError):
                raise
            raise ProxycodecError(f"bad predictor configuration: {e}") from None


class ProxyLeafMLP(nn.Module):
    """The supplement's "Proxy&Leaf (MLP)" (section 8.3, Table 5), set up like MAE: the reference proxy token
    (unmasked: its feature and position) and the masked target leaf token (a learned mask token and the leaf's
    position) are fed jointly to an MLP that outputs the leaf's feature directly, not a proxy -> leaf residual.

    [D] Tokens carry NeRF-style positional encodings of the absolute positions, normalised by the scene's centre and
    radius as the resolution embedding does (MAE's absolute position embeddings), with ``pe_pos_freqs`` = 8 so the
    finest period is about two voxels; the MLP body is the residual predictor's (encoder, ``n_blocks`` residual
    blocks of width ``hidden``), its head an ordinary linear layer. With an MLP the mask token is a learned constant
    input (equivalent to a bias), kept for fidelity to the MAE setup. Same ``predict`` interface as
    :class:`ResidualPredictor`, so stage 2 trains it with the same code.
    """

    def __init__(self, config: ProxyLeafConfig = ProxyLeafConfig()):
        super().__init__()
        self.config = config
        h = config.hidden
        self.mask_token = nn.Parameter(torch.randn(config.feat_dim) * 0.02)
        self.encoder = nn.Sequential(nn.Linear(2 * config.n_token, h), nn.ReLU())
        self.blocks = nn.ModuleList(_Block(h) for _ in range(config.n_blocks))
        self.head = nn.Linear(h, config.feat_dim)

    def _pe(self, p: torch.Tensor) -> torch.Tensor:
        cfg = self.config
        c = upload(cfg.scene_center, p.device, p.dtype)
        return positional_encoding(((p - c) / cfg.scene_radius).clamp(-4.0, 4.0), cfg.pe_pos_freqs)

    def geometry(self, leaf_positions: torch.Tensor, proxy_positions: torch.Tensor) -> torch.Tensor:
        """[L, 2 x 3 (1 + 2 Lp)]: PE(proxy position), PE(leaf position)."""
        return torch.cat([self._pe(proxy_positions), self._pe(leaf_positions)], -1)

    def forward(self, proxy_features: torch.Tensor, geometry: torch.Tensor,
                proxy_offsets: torch.Tensor | None = None) -> tuple[torch.Tensor, None]:
        n_pe = geometry.shape[1] // 2
        proxy_tok = torch.cat([proxy_features, geometry[:, :n_pe]], -1)
        leaf_tok = torch.cat([self.mask_token.expand(proxy_features.shape[0], -1), geometry[:, n_pe:]], -1)
        x = self.encoder(torch.cat([proxy_tok, leaf_tok], -1))
        for b in self.blocks:
            x = b(x)
        return self.head(x), None

    def predict(self, positions: torch.Tensor, features: torch.Tensor, nearest: torch.Tensor,
                leaves: torch.Tensor, offsets: torch.Tensor | None = None, encodings: torch.Tensor | None = None):
        """As ``ResidualPredictor.predict``; ``encodings`` is not used (this one encodes absolute positions)."""
        k = nearest_column(nearest)[leaves]
        return self(gather_rows(features, k), self.geometry(positions[leaves], positions[k]))

    def state_arrays(self) -> dict[str, np.ndarray]:
        return state_arrays(self)

    @classmethod
    def from_arrays(cls, config: ProxyLeafConfig, arrays: dict[str, np.ndarray]) -> "ProxyLeafMLP":
        return load_state_arrays(cls(config), arrays, "predictor")  # type: ignore[return-value]


def predictor_from_json(d: dict, arrays: dict[str, np.ndarray] | None = None):
    """A leaf predictor (residual or Proxy&Leaf MLP, told apart by ``kind``) from its JSON configuration, with its
    weights when ``arrays`` is given (else freshly initialised)."""
    if isinstance(d, dict) and d.get("kind", "residual") == "proxy-leaf-mlp":
        cfg, cls = ProxyLeafConfig.from_json(d), ProxyLeafMLP
    elif isinstance(d, dict) and d.get("kind", "residual") == "residual":
        cfg, cls = PredictorConfig.from_json(d), ResidualPredictor
    else:
        raise ProxycodecError(f"unknown predictor kind {d.get('kind') if isinstance(d, dict) else d!r}")
    return cls(cfg) if arrays is None else cls.from_arrays(cfg, arrays)


# ---------------------------------------------------------------------------------------------- training
@dataclass(frozen=True)
class TrainConfig:
    iters: int = 2000
    lr: float = 2e-3
    lr_final: float = 2e-4  # cosine decay to this
    sample_frac: float = 0.2  # leaves per iteration [S Fig. 12]
    offset_weight: float = 1.0  # weight of the offset MSE when offsets are predicted
    seed: int = 0

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class TrainResult:
    baseline_loss: float  # L_recon of the proxy-copy prediction over all leaves
    final_loss: float  # L_recon of the trained predictor over all leaves
    iters: int
    seconds: float
    history: list[tuple[int, float]]


@contextlib.contextmanager
def torch_threads(n: int):
    """Run a block with ``n`` intra-op threads (restored after).

    The predictor is small: one thread is faster than two fighting over the cores (OpenMP spin-waiting under load made
    a 1 s fit take 50 s on a busy 2-core machine), and a fixed thread count keeps float results reproducible.
    """
    old = torch.get_num_threads()
    if old == n:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


ProgressFn = Callable[[int, int, float, float], None]  # (iteration, total, loss, seconds elapsed)


def train_predictor(
    predictor: ResidualPredictor,
    positions: torch.Tensor,  # [M, 3] (what the decoder will see)
    features: torch.Tensor,  # [M, F]: proxies' rows are the inputs (quantised as stored), leaves' the targets
    proxy_mask,  # [M] bool
    nearest=None,  # [M] from nearest_proxy (computed when None)
    *,
    offsets: torch.Tensor | None = None,  # [M, K, 3], needed when the predictor predicts offsets
    config: TrainConfig = TrainConfig(),
    progress: ProgressFn | None = None,
    progress_every: int = 100,
    recon: str = "mse+cos",
) -> TrainResult:
    """Fit ``predictor`` (in place) to the scene's own leaves with Adam on L_recon, 20% of leaves per iteration.

    ``recon``: the L_recon variant (``RECON_LOSSES``). ``predictor`` may also be a :class:`ProxyLeafMLP`."""
    t0 = time.perf_counter()
    cfg = predictor.config
    dev = positions.device  # the predictor is trained where the scene lies
    predictor.to(dev)
    mask_np = np.asarray(proxy_mask.cpu() if isinstance(proxy_mask, torch.Tensor) else proxy_mask, dtype=bool)
    mask = torch.from_numpy(mask_np).to(dev)
    if nearest is None:
        nearest = predictor_neighbours(positions, mask_np, cfg)
    nearest = torch.as_tensor(np.asarray(nearest.cpu() if isinstance(nearest, torch.Tensor) else nearest),
                              dtype=torch.long).to(dev)
    leaves = (~mask).nonzero().squeeze(1)
    positions = positions.detach().float()
    features = features.detach().float()
    offsets = None if offsets is None else offsets.detach().float()
    k = nearest_column(nearest)[leaves]
    if isinstance(predictor, ProxyLeafMLP):
        geo = predictor.geometry(positions[leaves], positions[k])
    else:
        geo = predictor_geometry(positions, features, nearest, leaves, cfg)
    f_in, f_tgt = features[k], features[leaves]
    o_in = offsets[k] if (cfg.predict_offsets and offsets is not None) else None
    o_tgt = offsets[leaves] if o_in is not None else None
    if cfg.predict_offsets and offsets is None:
        raise ProxycodecError("the predictor predicts offsets: train_predictor needs offsets")

    def loss_of(idx=None):
        sl = slice(None) if idx is None else idx
        fp, op = predictor(f_in[sl], geo[sl], None if o_in is None else o_in[sl])
        loss = recon_loss(fp, f_tgt[sl], kind=recon)
        if op is not None:
            loss = loss + config.offset_weight * offset_recon_loss(op, o_tgt[sl])
        return loss

    with torch_threads(1):
        return _train(predictor, loss_of, int(leaves.numel()), config, progress, progress_every, t0)


def _train(predictor, loss_of, L, config, progress, progress_every, t0) -> TrainResult:
    with torch.no_grad():
        baseline = float(loss_of()) if L else 0.0
    history: list[tuple[int, float]] = []
    if L == 0 or config.iters <= 0:
        return TrainResult(baseline, baseline, 0, time.perf_counter() - t0, history)
    gen = torch.Generator().manual_seed(int(config.seed))
    torch.manual_seed(int(config.seed))
    opt = Adam(((k, p) for k, p in predictor.named_parameters() if p.requires_grad), eps=1e-8)
    n = max(1, int(math.ceil(config.sample_frac * L)))
    predictor.train()
    for it in range(1, config.iters + 1):
        t = (it - 1) / max(1, config.iters - 1)
        lr = config.lr_final + 0.5 * (config.lr - config.lr_final) * (1 + math.cos(math.pi * t))
        idx = torch.randperm(L, generator=gen)[:n].to(module_device(predictor))
        loss = loss_of(idx)
        opt.zero_grad()
        loss.backward()
        opt.step(lr)
        if it % progress_every == 0 or it == config.iters:
            history.append((it, float(loss.detach())))
            if progress is not None:
                progress(it, config.iters, history[-1][1], time.perf_counter() - t0)
    predictor.eval()
    with torch.no_grad():
        final = float(loss_of())
    return TrainResult(baseline, final, config.iters, time.perf_counter() - t0, history)


def load_fitted_predictor(weights_path) -> tuple[ResidualPredictor | None, np.ndarray | None]:
    """(predictor, proxy mask) stored by ``fit`` stage 2 in a weights sidecar, or (None, None) when it has none.

    Also (None, None) for the Proxy&Leaf MLP ablation (``fit --predictor proxy-leaf-mlp``): the container stores
    residual predictors only, so ``encode`` selects proxies and fits a residual predictor of its own for such a scene
    (its PLY already holds the leaves' predicted features, which is what ``eval`` measures)."""
    c = read_container(weights_path)
    fit_meta = c.meta.get("fit", {})
    if "predictor" not in fit_meta:
        return None, None
    if isinstance(fit_meta["predictor"], dict) and fit_meta["predictor"].get("kind", "residual") != "residual":
        return None, None
    cfg = PredictorConfig.from_json(fit_meta["predictor"])
    pred = ResidualPredictor.from_arrays(cfg, {k[len("predictor/"):]: v for k, v in c.arrays.items()
                                               if k.startswith("predictor/")})
    return pred.eval(), np.asarray(c.arrays["proxy_mask"], dtype=bool)
