"""Which torch device a command computes on: ``--device auto|cpu|cuda`` or ``$PROXYCODEC_DEVICE``.

The command line resolves the name once (``resolve``) and hands the ``torch.device`` to the library, whose functions
take ``device=`` where they create tensors and otherwise follow the tensors they are given (a scene's device). Only
this module names a device type; ``tests/test_devices.py`` checks that no other library module does.

``auto`` is ``cuda`` when torch sees a CUDA GPU and gsplat (the CUDA compositor) imports, else ``cpu``. ``cuda``
without a GPU, or without gsplat, is an error, not a silent fallback.

Importing this module does not import torch (the torch-free ``decode`` path imports it through the CLI).
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from .errors import ProxycodecError

if TYPE_CHECKING:
    import torch

#: Environment variable naming the device; the command line's ``--device`` sets it, so child processes inherit it.
ENV = "PROXYCODEC_DEVICE"
CHOICES = ("auto", "cpu", "cuda")
CPU = "cpu"
CUDA = "cuda"


def name_from_env() -> str:
    """``$PROXYCODEC_DEVICE`` (checked), or ``auto``."""
    text = os.environ.get(ENV, "").strip().lower() or "auto"
    if text not in CHOICES:
        raise ProxycodecError(f"{ENV} must be one of {', '.join(CHOICES)}, got {text!r}")
    return text


def cuda_unavailable_reason() -> str | None:
    """None when CUDA work can run here (torch sees a GPU and gsplat imports), else why not."""
    import torch

    if not torch.cuda.is_available():
        built = torch.version.cuda
        return ("torch sees no CUDA GPU" if built else
                f"this torch ({torch.__version__}) is built without CUDA")
    try:
        import gsplat  # noqa: F401
    except ImportError as e:
        return f"gsplat, the CUDA compositor, does not import ({e}); pip install gsplat"
    return None


def resolve(name: str | None = None) -> torch.device:
    """``auto`` / ``cpu`` / ``cuda`` (None: ``$PROXYCODEC_DEVICE``, else ``auto``) -> a ``torch.device``."""
    import torch

    name = name_from_env() if name is None else str(name).strip().lower()
    if name not in CHOICES:
        raise ProxycodecError(f"unknown device {name!r}; choose from {', '.join(CHOICES)}")
    if name == CPU:
        return torch.device(CPU)
    why = cuda_unavailable_reason()
    if name == CUDA and why is not None:
        raise ProxycodecError(f"--device cuda: {why}")
    return torch.device(CUDA if why is None else CPU)


def as_device(device: torch.device | str | None) -> torch.device:
    """A function's ``device=`` argument as a ``torch.device`` (None: the CPU, torch's own default)."""
    import torch

    return torch.device(CPU) if device is None else torch.device(device)


def module_device(module) -> torch.device:
    """Where a torch module's parameters lie (the CPU for a module without any)."""
    import torch

    return next(iter(module.parameters()), torch.empty(0)).device


def synchronize(device: torch.device | str | None) -> None:
    """Wait for the device's queued work (timings of CUDA work); nothing on the CPU."""
    if device is not None and as_device(device).type == CUDA:
        import torch

        torch.cuda.synchronize(as_device(device))


def generator(device: torch.device | str | None, seed: int) -> torch.Generator:
    """A torch generator on ``device`` seeded with ``seed`` (random draws made where they are used)."""
    import torch

    d = as_device(device)
    g = torch.Generator(device=d) if d.type != CPU else torch.Generator()
    return g.manual_seed(int(seed))


def upload(data, device, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``data`` (a host array, list, number or tensor) as a tensor on ``device``, in ``dtype`` where given.

    The host-to-device copy is queued without waiting (``non_blocking``): torch's default copy first waits for every
    kernel queued before it, a full synchronisation of the host with the GPU for a few bytes, and a training step
    uploads a dozen such small tables (camera pose, frustum planes, resize weights, the leaf sample). From pageable
    memory CUDA stages the bytes before the call returns, so ``data`` may change or go right after. The values are
    those of a blocking copy. On the CPU nothing is copied: as with ``torch.as_tensor``, the tensor may share
    ``data``'s memory."""
    import torch

    return torch.as_tensor(data, dtype=dtype).to(device, non_blocking=True)
