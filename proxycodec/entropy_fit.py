"""The encoder's half of the entropy model (torch): float twins of ``entropy.IntNet``, the rate they assign, their
fit to a scene's symbols, and their conversion to the integer nets the container stores.

The float net sees the same integer inputs as the integer one (divided by 128) and outputs, per symbol, a centre and
a scale level; its rate is the discrete Laplace probability of the symbol (``laplace_bits``). After fitting, each
layer is re-expressed in integers (``to_int``): int8 weights with a power-of-two scale per layer, activations
re-scaled by shifts chosen from the activations' 99.9th percentile on the scene itself. The integer net is what
both encoder and decoder evaluate: rounding it only moves probabilities (a few bits), never correctness.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch

from . import entropy as ent
from .devices import as_device
from .sections import LEVEL_DIVISOR, LEVEL_MAX, level_multipliers, position_cells

INPUT_SCALE = 128.0


class FloatNet(torch.nn.Module):
    def __init__(self, n_in: int, n_out: int, hidden: int, with_base: bool):
        super().__init__()
        self.layers = torch.nn.ModuleList([torch.nn.Linear(n_in, hidden), torch.nn.Linear(hidden, hidden),
                                           torch.nn.Linear(hidden, 2 * n_out)])
        self.gain = torch.nn.Parameter(torch.zeros(n_out), requires_grad=with_base)
        self.n_out = n_out

    def forward(self, x: torch.Tensor, base: torch.Tensor | None = None):
        h = x / INPUT_SCALE
        for i, lin in enumerate(self.layers):
            h = lin(h)
            if i < len(self.layers) - 1:
                h = torch.relu(h)
        mu = h[:, :self.n_out]
        if base is not None:
            mu = mu + self.gain * base
        return mu, h[:, self.n_out:]


def laplace_bits(y: torch.Tensor, mu: torch.Tensor, level: torch.Tensor) -> torch.Tensor:
    """-log2 P(y) per symbol for a Laplace(mu, b) integrated over [y - 1/2, y + 1/2], b from the (continuous) scale
    level as the tables define it. ``y`` may carry uniform noise (training) or be integers (measuring)."""
    b = torch.exp(ent.LN_B0 + level.clamp(-2.0, ent.SCALE_LEVELS + 1.0) / ent.LN_STEP)

    def cdf(v):
        z = (v - mu) / b
        return torch.where(z < 0, 0.5 * torch.exp(z.clamp(max=0)), 1 - 0.5 * torch.exp(-z.clamp(min=0)))

    p = cdf(y + 0.5) - cdf(y - 0.5)
    return -torch.log2(p.clamp_min(1e-9))


@dataclass
class Sample:
    """One pass's training data: integer inputs, base (or None), the centred symbols it codes."""

    net: str
    x: np.ndarray
    base: np.ndarray | None
    y: np.ndarray


def samples(ctx: ent.Context, a: ent.Attributes) -> list[Sample]:
    """Every coding pass's inputs and targets, exactly as the decoder will see them (the symbols are lossless)."""
    out: list[Sample] = []
    pending: list[tuple] = []
    shifts = ent.input_shifts(a)
    known = ent.Attributes(a.features.copy(), a.scalings.copy(), a.offsets.copy())

    def predict(name, x, base):
        pending.append((name, x, base))
        n = ent.net_inputs(a.features.shape[1], a.offsets.shape[1] // 3)[name][1]
        z = np.zeros((len(x), n), np.int64)
        return z, z

    def code(attr, rows, cols, m, s):
        vals = getattr(known, attr)[rows][:, cols]
        name, x, base = pending.pop()
        out.append(Sample(name, x, base, vals))
        return vals

    ent.passes(ctx, predict, shifts, ent.Attributes(np.zeros_like(a.features), np.zeros_like(a.scalings),
                                                    np.zeros_like(a.offsets)), code)
    return out


def _net_data(data: list, name: str, n_out: int):
    """One net's training data: (inputs, targets padded to the net's outputs, bases, mask of the real targets)."""
    xs, ys, bs, ms = [], [], [], []
    for s in data:
        if s.net != name:
            continue
        c = s.y.shape[1]
        y = np.zeros((len(s.y), n_out), np.float32)
        y[:, :c] = s.y
        mk = np.zeros((len(s.y), n_out), np.float32)
        mk[:, :c] = 1
        xs.append(s.x)
        ys.append(y)
        ms.append(mk)
        bs.append(np.zeros((len(s.y), n_out)) if s.base is None else s.base)
    return (torch.from_numpy(np.concatenate(xs).astype(np.float32)), torch.from_numpy(np.concatenate(ys)),
            torch.from_numpy(np.concatenate(bs).astype(np.float32)), torch.from_numpy(np.concatenate(ms)))


def _channel_start(Y: torch.Tensor, Mk: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each channel's mean and its Laplace scale level from its spread: where every net starts (order 0)."""
    w = Mk.sum(0).clamp_min(1)
    mean = (Y * Mk).sum(0) / w
    sd = (((Y - mean) ** 2 * Mk).sum(0) / w).sqrt()
    return mean, (torch.log(sd / math.sqrt(2) + 0.5) - ent.LN_B0) * ent.LN_STEP


@torch.no_grad()
def start_bytes(ctx: ent.Context, a: ent.Attributes) -> float:
    """Bytes of the scene's symbols under the nets' starting point (a discrete Laplace per channel at its mean and
    spread, no context): what the fitted model improves on. Seconds on lego; no fitting."""
    F, K = a.features.shape[1], a.offsets.shape[1] // 3
    sizes = ent.net_inputs(F, K)
    data = samples(ctx, a)
    total = 0.0
    for name in ent.NETS:
        _, Y, _, Mk = _net_data(data, name, sizes[name][1])
        mean, lvl = _channel_start(Y, Mk)
        total += float((laplace_bits(Y, mean.expand_as(Y), lvl.expand_as(Y)) * Mk).sum()) / 8
    return total


def fit_nets(ctx: ent.Context, a: ent.Attributes, *, hidden: int = 16, iters: int = 1500, lr: float = 3e-3,
             seed: int = 0, batch: int = 16384, progress=None, device=None
             ) -> tuple[dict[str, ent.IntNet], dict[str, float]]:
    """Fit the three float nets to the scene's symbols (Adam on the rate) on ``device`` (None: the CPU; the
    batches are drawn on the CPU either way), convert them to integer nets (on the CPU: the integer nets are the
    format). Returns the nets and the float model's estimated bytes per net."""
    F, K = a.features.shape[1], a.offsets.shape[1] // 3
    sizes = ent.net_inputs(F, K)
    data = samples(ctx, a)
    g = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    nets: dict[str, ent.IntNet] = {}
    estimate: dict[str, float] = {}
    for name in ent.NETS:
        n_in, n_out = sizes[name]
        with_base = name != "features"
        net = FloatNet(n_in, n_out, hidden, with_base).to(as_device(device))
        X, Y, B, Mk = (t.to(as_device(device)) for t in _net_data(data, name, n_out))
        if len(X) == 0:
            nets[name] = to_int(net, X)
            estimate[name] = 0.0
            continue
        with torch.no_grad():  # start at each channel's mean and spread
            net.layers[-1].bias[:n_out], net.layers[-1].bias[n_out:] = _channel_start(Y, Mk)
        opt = torch.optim.Adam(net.parameters(), lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, iters, eta_min=lr * 0.1)
        n = len(X)
        for it in range(iters):
            sel = torch.randint(0, n, (min(batch, n),), generator=g).to(X.device) if n > batch else slice(None)
            mu, lvl = net(X[sel], B[sel] if with_base else None)
            loss = (laplace_bits(Y[sel], mu, lvl) * Mk[sel]).sum() / Mk[sel].sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            if progress and (it + 1) % 500 == 0:
                progress(f"entropy model {name}: {it + 1}/{iters}, {loss.item():.3f} bits/symbol")
        with torch.no_grad():
            mu, lvl = net(X, B if with_base else None)
            estimate[name] = float((laplace_bits(Y, mu, lvl) * Mk).sum()) / 8
        nets[name] = to_int(net.cpu(), X.cpu())
    return nets, estimate


def _exp_for(w_abs_max: float, limit: float = 127.0, cap: int = 24) -> int:
    if w_abs_max <= 0:
        return cap
    return max(0, min(cap, math.floor(math.log2(limit / w_abs_max))))


def to_int(net: FloatNet, X: torch.Tensor) -> ent.IntNet:
    """The float net in integers (see the module's docstring); ``X`` (the scene's inputs) calibrates the shifts."""
    Ws, bs, shifts = [], [], []
    g_in = INPUT_SCALE  # float value = integer / g_in
    h = X / INPUT_SCALE
    n_layers = len(net.layers)
    with torch.no_grad():
        for i, lin in enumerate(net.layers):
            W = lin.weight.double() / g_in
            b = lin.bias.double()
            last = i == n_layers - 1
            e = _exp_for(float(W.abs().max()), cap=ent.MAX_SHIFT if last else 24)
            if last:
                e = max(1, e)
            Wq = torch.round(W * 2.0**e).clamp(-127, 127).to(torch.int8)
            bq = torch.round(b * 2.0**e).clamp(-(1 << 22), 1 << 22).to(torch.int64)
            Ws.append(Wq.numpy())
            bs.append(bq.numpy())
            if last:
                gain = torch.round(net.gain.double() * 2.0**e).clamp(-(1 << 29), 1 << 29).to(torch.int64).numpy()
                return ent.IntNet(tuple(Ws), tuple(bs), tuple(shifts), e, gain)
            h = torch.relu(lin(h))
            p = float(torch.quantile(h.flatten()[:1 << 20], 0.999)) if h.numel() else 1.0
            k = _exp_for(max(p, 1e-6))  # float h * 2^k fits in 127
            t = max(0, e - k)
            shifts.append(t)
            g_in = 2.0 ** (e - t)
    raise AssertionError("unreachable")


# ---------------------------------------------------------------------------------------------- rate in the loss
ATTR_CHANNELS = ("features", "scalings", "offsets")


class RateModel(torch.nn.Module):
    """The rate term of training (``fit --lambda-rate``, encode's distillation): quantisation on a learned grid per
    attribute channel (``origin + k step``), and the bits of the symbols under float twins of the entropy model's nets.

    ``forward`` returns the attributes rounded to their grids with a straight-through gradient (what the container
    will store, exactly: encode quantises on the same grids; the step's gradient is LSQ's, ``round(v) - v``) and an
    estimate of the total bits of the stored attributes, with uniform noise in place of rounding (the usual
    differentiable proxy), from a random sample of proxies and leaves scaled to their counts. The nets' inputs
    (contexts) are detached: the rate's gradient reaches the coded values, their steps and the nets."""

    def __init__(self, positions: np.ndarray, voxel: float, mask: np.ndarray, features: torch.Tensor,
                 offsets: torch.Tensor, scalings: torch.Tensor, *, bits: int = 8, hidden: int = 32,
                 sample: int = 2048, cells: int = 0):
        super().__init__()
        self.cells = int(cells)
        if self.cells:  # per-cell levels (scene format 5): an anchor's step is its channel's x 2^(level / 4)
            self.register_buffer("cell", torch.from_numpy(position_cells(positions, voxel, self.cells)))
            self.register_buffer("kind", torch.from_numpy((~np.asarray(mask, bool)).astype(np.int64)))
            self.register_buffer("multipliers", torch.from_numpy(level_multipliers()).float())
            self.levels = torch.nn.ParameterDict({k: torch.nn.Parameter(torch.zeros(2, self.cells ** 3))
                                                  for k in ATTR_CHANNELS})
        ctx = ent.Context.of(np.asarray(positions, np.float32), voxel, np.asarray(mask, bool))
        self.register_buffer("posn", torch.from_numpy(ctx.posn).float())
        self.register_buffer("rel", torch.from_numpy(ctx.rel).float())
        self.register_buffer("near", torch.from_numpy(ctx.near))
        self.register_buffer("proxies", torch.from_numpy(ctx.proxies))
        self.register_buffer("leaves", torch.from_numpy(ctx.leaves))
        self.sample = sample
        self.log_step = torch.nn.ParameterDict()
        M = len(mask)
        F, K = features.shape[1], offsets.shape[1]
        values = {"features": features.detach()[self.proxies], "scalings": scalings.detach(),
                  "offsets": offsets.detach().reshape(M, 3 * K)}
        for k, x in values.items():
            lo, hi = x.min(0).values, x.max(0).values
            step = ((hi - lo) / ((1 << bits) - 1)).clamp_min(1e-6)
            self.log_step[k] = torch.nn.Parameter(torch.log(step))
            self.register_buffer(f"mid_{k}", (lo + hi) / 2)
        self.nets = torch.nn.ModuleDict({name: FloatNet(n_in, n_out, hidden, name != "features")
                                         for name, (n_in, n_out) in ent.net_inputs(F, K).items()})
        for name, net in self.nets.items():  # start at each channel's spread (uniform over the 2^bits levels)
            with torch.no_grad():
                net.layers[-1].bias[net.n_out:] = (math.log((1 << bits) / 4) - ent.LN_B0) * ent.LN_STEP

    def grids(self) -> dict[str, dict]:
        """Per attribute: the quantisation grid, ``{"step": [C], "origin": [C]}`` (``quant_steps`` metadata), and
        with per-cell levels ``"levels": {"cells": G, "table": [2 G^3]}`` (``sections.level_table``)."""
        out = {k: {"step": [float(x) for x in torch.exp(v).detach().double()],
                   "origin": [float(x) for x in getattr(self, f"mid_{k}").double()]}
               for k, v in self.log_step.items()}
        if self.cells:
            for k, u in self.levels.items():
                table = torch.round(u.detach().clamp(-LEVEL_MAX, LEVEL_MAX)).long()
                out[k]["levels"] = {"cells": self.cells, "table": [int(v) for v in table.flatten()]}
        return out

    def step_of(self, k: str) -> torch.Tensor:
        """[C] (per channel) or [M, C] (per anchor, with per-cell levels): the grid steps of attribute ``k``; the
        levels' multipliers are exactly the decoder's (``sections.level_multipliers``), their gradient
        straight-through (that of ``2^(level / 4)`` at the rounded level)."""
        step = torch.exp(self.log_step[k])
        if not self.cells:
            return step
        u = self.levels[k][0 if k == "features" else self.kind, self.cell].clamp(-LEVEL_MAX, LEVEL_MAX)
        m = self.multipliers[(torch.round(u).long() + LEVEL_MAX)]
        m = m + (m * (math.log(2) / LEVEL_DIVISOR)).detach() * (u - u.detach())
        return step * m[:, None]

    def symbol_bits(self, y_f: torch.Tensor, y_s: torch.Tensor, y_o: torch.Tensor, P_rows: torch.Tensor,
                    L_rows: torch.Tensor, wp: float = 1.0, wl: float = 1.0) -> torch.Tensor:
        """The bits of the (noisy, continuous) symbols ``y_f`` [M, F], ``y_s`` [M, 6], ``y_o`` [M, 3K] of the
        proxies ``P_rows`` and the leaves ``L_rows`` under the float nets, in the passes the decoder makes: wp x
        the proxies' sum + wl x the leaves'. The contexts (nets' inputs) are detached.

        Each net runs once, over the stacked rows of all its passes (the feature groups; proxies and leaves), and
        every symbol goes through one ``laplace_bits`` call: a pass's own call was ~40 operations forward and
        backward, each a kernel launch on a GPU, and a row's outputs do not depend on the rows beside it
        (``tests/test_entropy.py`` holds the pass-by-pass reference)."""

        def clip(v):
            return v.detach().clamp(-ent.ACT_MAX, ent.ACT_MAX)

        F = y_f.shape[1]
        nP, nL = len(P_rows), len(L_rows)
        G, FG = -(-F // ent.FEATURE_GROUP), ent.FEATURE_GROUP
        yp = y_f[P_rows]
        # group g's context: the earlier groups' (clipped) values, the later ones 0, and its one-hot 64
        known = torch.where(self._group_known(G, F, yp.device), clip(yp)[None], 0.0)  # [G, nP, F]
        head = torch.cat([self.posn[P_rows][None].expand(G, -1, -1), known,
                          self._group_onehot(G, yp.device, yp.dtype).expand(-1, nP, -1)], 2)
        mu, lvl = self.nets["features"](head.reshape(G * nP, -1))
        mu, lvl = mu.reshape(G, nP, FG), lvl.reshape(G, nP, FG)
        if F == G * FG:
            terms_p = [(yp.reshape(nP, G, FG).transpose(0, 1), mu, lvl)]
        else:  # a short last group: its outputs beyond its channels are not symbols
            terms_p = [(yp[:, g * FG:(g + 1) * FG], mu[g, :, :min(FG, F - g * FG)], lvl[g, :, :min(FG, F - g * FG)])
                       for g in range(G)]
        rows = torch.cat([P_rows, L_rows])
        src = torch.cat([P_rows, self.near[L_rows]])
        flag = torch.cat([y_s.new_zeros(nP, 1), y_s.new_full((nL, 1), float(ent.FLAG))])
        head = [clip(y_f)[src], self.posn[rows], flag, self.rel[rows]]
        ref_s = torch.cat([y_s.new_zeros(nP, y_s.shape[1]), y_s[src[nP:]].detach()])
        ref_o = torch.cat([y_o.new_zeros(nP, y_o.shape[1]), y_o[src[nP:]].detach()])
        y_sr, y_or = y_s[rows], y_o[rows]
        mu_s, lvl_s = self.nets["scalings"](torch.cat(head + [clip(ref_s)], 1), ref_s)
        mu_o, lvl_o = self.nets["offsets"](torch.cat(head + [clip(y_sr), clip(ref_o)], 1), ref_o)
        terms_p += [(y_sr[:nP], mu_s[:nP], lvl_s[:nP]), (y_or[:nP], mu_o[:nP], lvl_o[:nP])]
        terms_l = [(y_sr[nP:], mu_s[nP:], lvl_s[nP:]), (y_or[nP:], mu_o[nP:], lvl_o[nP:])] if nL else []
        flat = [torch.cat([t[i].reshape(-1) for t in terms_p + terms_l]) for i in range(3)]
        b = laplace_bits(*flat)
        n_p = sum(t[0].numel() for t in terms_p)
        return wp * b[:n_p].sum() + wl * b[n_p:].sum()

    @staticmethod
    @functools.lru_cache(maxsize=16)
    def _group_known(G: int, F: int, device: torch.device) -> torch.Tensor:
        """[G, 1, F] bool: feature group g's context, the channels of the groups before it (made once per device,
        a normal tensor even under ``torch.inference_mode``, as ``decoder._frequencies``)."""
        with torch.inference_mode(False), torch.no_grad():
            c = torch.arange(F, device=device)
            return (c[None, :] < (torch.arange(G, device=device) * ent.FEATURE_GROUP)[:, None])[:, None, :]

    @staticmethod
    @functools.lru_cache(maxsize=16)
    def _group_onehot(G: int, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
        """[G, 1, G]: feature group g's one-hot input (64 at g)."""
        with torch.inference_mode(False), torch.no_grad():
            return (torch.eye(G, device=device, dtype=dtype) * 64)[:, None, :]

    @torch.no_grad()
    def rounded(self, features: torch.Tensor, offsets: torch.Tensor, scalings: torch.Tensor):
        """(features, offsets, scalings) on their grids: what training renders and the container stores."""
        M, K = offsets.shape[:2]
        out = []
        for k, x in (("features", features), ("offsets", offsets.reshape(M, 3 * K)), ("scalings", scalings)):
            step, mid = self.step_of(k), getattr(self, f"mid_{k}")
            out.append(mid + torch.round((x - mid) / step) * step)
        return out[0], out[1].reshape(M, K, 3), out[2]

    def forward(self, features: torch.Tensor, offsets: torch.Tensor, scalings: torch.Tensor, generator=None):
        M, K = offsets.shape[:2]
        st = {k: self.step_of(k) for k in self.log_step}
        o2 = offsets.reshape(M, 3 * K)
        v_f = (features - self.mid_features) / st["features"]  # continuous symbols; features: the proxies' rows
        v_s = (scalings - self.mid_scalings) / st["scalings"]
        v_o = (o2 - self.mid_offsets) / st["offsets"]

        def rounded(v, mid, step):  # straight through: forward on the grid, backward as identity in v
            return mid + (v + (torch.round(v) - v).detach()) * step

        q_f = rounded(v_f, self.mid_features, st["features"])
        q_s = rounded(v_s, self.mid_scalings, st["scalings"])
        q_o = rounded(v_o, self.mid_offsets, st["offsets"]).reshape(M, K, 3)
        y_f = v_f + torch.rand(v_f.shape, generator=generator, device=v_f.device) - 0.5
        y_s = v_s + torch.rand(v_s.shape, generator=generator, device=v_s.device) - 0.5
        y_o = v_o + torch.rand(v_o.shape, generator=generator, device=v_o.device) - 0.5

        def pick(idx):
            n = len(idx)
            if n <= self.sample:
                return idx, 1.0
            sel = torch.randperm(n, generator=generator, device=idx.device)[:self.sample]
            return idx[sel], n / self.sample

        P_rows, wp = pick(self.proxies)
        L_rows, wl = pick(self.leaves)
        bits = self.symbol_bits(y_f, y_s, y_o, P_rows, L_rows, wp, wl)
        return q_f, q_o, q_s, bits
