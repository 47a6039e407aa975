"""Raw-array persistence of torch modules: ``state_dict`` <-> ``{name: float32 ndarray}``. Never pickle.

torch is imported by the functions that need it: ``check_arrays`` also serves the torch-free decode path
(``proxycodec.lite``), which checks a container's weights exactly as ``load_state_arrays`` does.
"""

from __future__ import annotations

import numpy as np

from .errors import ProxycodecError


def state_arrays(module) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().float().numpy().copy() for k, v in module.state_dict().items()}


def check_arrays(expected: dict[str, tuple[int, ...]], arrays: dict[str, np.ndarray],
                 what: str) -> dict[str, np.ndarray]:
    """``arrays`` checked against ``expected`` (name -> shape, in the module's order): names, shapes, finiteness
    (``what`` names the network in errors). Returns fresh float32 copies of the expected ones; others are ignored."""
    missing = sorted(set(expected) - set(arrays))
    if missing:
        raise ProxycodecError(f"{what} weights are missing {', '.join(missing[:4])}")
    out = {}
    for k, shape in expected.items():
        a = np.asarray(arrays[k])
        if tuple(a.shape) != tuple(shape):
            raise ProxycodecError(f"{what} weight {k} has shape {a.shape}, expected {tuple(shape)}")
        if not np.all(np.isfinite(a)):
            raise ProxycodecError(f"{what} weight {k} contains NaN or Inf")
        out[k] = np.array(a, dtype=np.float32, copy=True)
    return out


def load_state_arrays(module, arrays: dict[str, np.ndarray], what: str):
    """Load ``arrays`` into ``module`` after checking names, shapes and finiteness (``what`` names it in errors)."""
    import torch

    expected = {k: tuple(v.shape) for k, v in module.state_dict().items()}
    checked = check_arrays(expected, arrays, what)
    module.load_state_dict({k: torch.from_numpy(v) for k, v in checked.items()})
    return module
