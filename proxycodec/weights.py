"""Raw-array persistence of torch modules: ``state_dict`` <-> ``{name: float32 ndarray}``. Never pickle."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from .errors import ProxycodecError


def state_arrays(module: nn.Module) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().float().numpy().copy() for k, v in module.state_dict().items()}


def load_state_arrays(module: nn.Module, arrays: dict[str, np.ndarray], what: str) -> nn.Module:
    """Load ``arrays`` into ``module`` after checking names, shapes and finiteness (``what`` names it in errors)."""
    expected = module.state_dict()
    missing = sorted(set(expected) - set(arrays))
    if missing:
        raise ProxycodecError(f"{what} weights are missing {', '.join(missing[:4])}")
    state = {}
    for k, ref in expected.items():
        a = np.asarray(arrays[k])
        if tuple(a.shape) != tuple(ref.shape):
            raise ProxycodecError(f"{what} weight {k} has shape {a.shape}, expected {tuple(ref.shape)}")
        if not np.all(np.isfinite(a)):
            raise ProxycodecError(f"{what} weight {k} contains NaN or Inf")
        state[k] = torch.from_numpy(np.array(a, dtype=np.float32, copy=True))
    module.load_state_dict(state)
    return module
