"""The one optimiser every trainer uses (anchor fit, predictor fit, explicit 3DGS), and its learning-rate schedule.

``Adam`` keeps named parameters whose rows can be appended or dropped between steps (anchor growing, 3DGS
densification), and its moments are plain tensors that serialise as raw arrays (checkpoints hold no pickle).
``torch.optim.Adam`` would need "optimiser surgery" for the first, pickling for the second, and importing
``torch.optim`` pulls in ``torch._dynamo``, which costs seconds in every fresh process that encodes.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .errors import ProxycodecError

__all__ = ["Adam", "exp_lr"]


def exp_lr(init: float, final: float, t: float) -> float:
    """Scaffold-GS's ``get_expon_lr_func`` without delay: log-linear from init to final as t goes 0 -> 1 (linear when
    either end is not positive)."""
    t = min(max(t, 0.0), 1.0)
    if init <= 0 or final <= 0:
        return init * (1 - t) + final * t
    return math.exp(math.log(init) * (1 - t) + math.log(final) * t)


class Adam:
    """Adam (Kingma & Ba, bias-corrected) over named tensors, each with its own step count and learning rate.

    ``eps`` defaults to 3DGS's 1e-15 (the scene trainers); the residual predictor uses torch's 1e-8. A parameter
    is stepped only when it has a gradient and a non-zero learning rate.
    """

    def __init__(self, params=(), betas=(0.9, 0.999), eps: float = 1e-15):
        self.b1, self.b2 = betas
        self.eps = eps
        self.params: dict[str, torch.Tensor] = {}
        self.m: dict[str, torch.Tensor] = {}
        self.v: dict[str, torch.Tensor] = {}
        self.step_count: dict[str, int] = {}
        for name, p in (params.items() if isinstance(params, dict) else params):
            self.add(name, p)

    def add(self, name: str, p: torch.Tensor) -> None:
        self.params[name] = p
        self.m.setdefault(name, torch.zeros_like(p.detach()))
        self.v.setdefault(name, torch.zeros_like(p.detach()))
        self.step_count.setdefault(name, 0)

    def rebind(self, name: str, p: torch.Tensor, keep: torch.Tensor | None = None, append: int = 0) -> None:
        """The tensor ``name`` was replaced: rows ``keep`` survive (in order), then ``append`` zero rows follow."""
        m, v = self.m[name], self.v[name]
        if keep is not None:
            m, v = m[keep], v[keep]
        if append:
            z = m.new_zeros((append,) + tuple(m.shape[1:]))
            m, v = torch.cat([m, z]), torch.cat([v, z])
        self.m[name], self.v[name] = m.contiguous(), v.contiguous()
        self.params[name] = p

    @torch.no_grad()
    def step(self, lrs: dict[str, float] | float) -> None:
        """One update; ``lrs``: a learning rate per parameter name (missing: 0), or one for all.

        Every stepped parameter goes through one ``torch._foreach_*`` call per Adam operation (8 in all), not 8
        calls each: on a GPU each call is a kernel launch, and the anchor fit's stage 2 steps 54 tensors. On the CPU
        the foreach calls run the same per-tensor operations, so the result is bitwise that of the loop
        ``step_reference`` (tested)."""
        live = self._live(lrs)
        if not live:
            return
        ps = [self.params[n] for n, _, _ in live]
        gs = [p.grad for p in ps]
        ms, vs = [self.m[n] for n, _, _ in live], [self.v[n] for n, _, _ in live]
        torch._foreach_mul_(ms, self.b1)
        torch._foreach_add_(ms, gs, alpha=1 - self.b1)
        torch._foreach_mul_(vs, self.b2)
        torch._foreach_addcmul_(vs, gs, gs, value=1 - self.b2)
        denom = torch._foreach_div(vs, [1 - self.b2**t for _, _, t in live])
        torch._foreach_sqrt_(denom)
        torch._foreach_add_(denom, self.eps)
        torch._foreach_addcdiv_(ps, ms, denom, [-lr / (1 - self.b1**t) for _, lr, t in live])

    @torch.no_grad()
    def step_reference(self, lrs: dict[str, float] | float) -> None:
        """``step`` as a loop over the parameters, one tensor at a time (the reference ``step`` is tested against)."""
        for name, lr, t in self._live(lrs):
            p, m, v = self.params[name], self.m[name], self.v[name]
            m.mul_(self.b1).add_(p.grad, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(p.grad, p.grad, value=1 - self.b2)
            denom = (v / (1 - self.b2**t)).sqrt_().add_(self.eps)
            p.addcdiv_(m, denom, value=-lr / (1 - self.b1**t))

    def _live(self, lrs: dict[str, float] | float) -> list[tuple[str, float, int]]:
        """(name, learning rate, step count after this step) of each parameter this step moves: those with a
        gradient and a non-zero rate; their step counts advance."""
        live = []
        for name, p in self.params.items():
            lr = float(lrs) if isinstance(lrs, (int, float)) else lrs.get(name, 0.0)
            if p.grad is None or lr == 0.0:
                continue
            self.step_count[name] += 1
            live.append((name, lr, self.step_count[name]))
        return live

    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def state_arrays(self) -> dict[str, np.ndarray]:
        out = {}
        for name in self.params:
            out[f"adam_m/{name}"] = self.m[name].cpu().numpy().copy()
            out[f"adam_v/{name}"] = self.v[name].cpu().numpy().copy()
        return out

    def load_arrays(self, arrays: dict[str, np.ndarray], steps: dict[str, int]) -> None:
        for name, p in self.params.items():
            for kind, store in (("adam_m", self.m), ("adam_v", self.v)):
                a = arrays.get(f"{kind}/{name}")
                if a is None or tuple(a.shape) != tuple(p.shape):
                    raise ProxycodecError(f"checkpoint optimiser state {kind}/{name} is missing or has a wrong shape")
                store[name] = torch.from_numpy(np.array(a, dtype=np.float32)).to(p.device)
            self.step_count[name] = int(steps.get(name, 0))
