"""Rendering: EWA projection with the coverage gate (torch), then a compositing backend.

Backends share one 2D interface (``Projected``): ``reference`` (pure torch, the oracle), ``cpu`` (numba kernels with
analytic backward) and ``cuda`` (gsplat, when installed and a CUDA device is present). ``auto`` picks by device.

Importing this package does not import torch (the functions do, when called): the numba kernels under it
(``_raster_kernels``, ``_project_kernels``) also serve the torch-free decode path, ``proxycodec.lite``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import ProxycodecError
from .project import GateConfig, Projected, project_gaussians

if TYPE_CHECKING:
    import torch

BACKENDS = ("auto", "reference", "cpu", "cuda")


@dataclass
class RenderResult:
    image: torch.Tensor  # [H, W, C]
    alpha: torch.Tensor  # [H, W]
    projected: Projected


def __getattr__(name: str):
    if name == "rasterize_reference":  # imports torch: loaded on first use
        from .reference import rasterize_reference

        return rasterize_reference
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def available_backends() -> list[str]:
    import torch

    out = ["reference"]
    try:
        from . import cpu  # noqa: F401

        out.append("cpu")
    except ImportError:
        pass
    if torch.cuda.is_available():
        try:
            import gsplat  # noqa: F401

            out.append("cuda")
        except ImportError:
            pass
    return out


def resolve_backend(backend: str, device: torch.device) -> str:
    if backend not in BACKENDS:
        raise ProxycodecError(f"unknown backend {backend!r}; choose from {', '.join(BACKENDS)}")
    avail = available_backends()
    if backend == "auto":
        if device.type == "cuda" and "cuda" in avail:
            return "cuda"
        if device.type == "cpu" and "cpu" in avail:
            return "cpu"
        return "reference"
    if backend not in avail:
        raise ProxycodecError(f"backend {backend!r} is not available here (available: {', '.join(avail)})")
    return backend


def rasterize(proj: Projected, background: torch.Tensor, backend: str = "auto") -> tuple[torch.Tensor, torch.Tensor]:
    """Composite a projected set of Gaussians -> (image [H, W, C], alpha [H, W])."""
    name = resolve_backend(backend, proj.means2d.device)
    args = (proj.means2d, proj.conics, proj.opacities, proj.colors, proj.depths, proj.extent,
            proj.width, proj.height, background)
    if name == "cpu":
        from .cpu import rasterize_cpu

        return rasterize_cpu(*args)
    if name == "cuda":
        from .cuda import rasterize_cuda

        return rasterize_cuda(*args)
    from .reference import rasterize_reference

    return rasterize_reference(*args)


def project(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera,
    *,
    gate: GateConfig = GateConfig(),
    near: float = 0.01,
    far: float = 1e10,
    origin=None,
    backend: str = "auto",
) -> Projected:
    """``project_gaussians`` on the path the backend implies: the fused numba projection (``project_cpu``, same
    result, analytic backward) when ``backend`` resolves to ``cpu`` and the tensors are on the CPU, else the torch
    reference."""
    name = resolve_backend(backend, means.device)
    if name == "cpu" and means.device.type == "cpu":
        from .project_cpu import project_gaussians_cpu

        return project_gaussians_cpu(means, quats, scales, opacities, colors, camera, gate=gate, near=near, far=far,
                                     origin=origin)
    return project_gaussians(means, quats, scales, opacities, colors, camera, gate=gate, near=near, far=far,
                             origin=origin)


def render_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera,
    *,
    background=(1.0, 1.0, 1.0),
    gate: GateConfig = GateConfig(),
    backend: str = "auto",
    near: float = 0.01,
) -> RenderResult:
    """Render explicit 3D Gaussians seen by ``camera`` (at the camera's own resolution)."""
    import torch

    bg = torch.as_tensor(background, dtype=means.dtype, device=means.device)
    proj = project(means, quats, scales, opacities, colors, camera, gate=gate, near=near, backend=backend)
    image, alpha = rasterize(proj, bg, backend)
    return RenderResult(image, alpha, proj)


def warm_up(backend: str = "auto", device=None) -> float:
    """Render a fixed 64-Gaussian scene at 32 x 32 pixels and back-propagate through it, in float32 on ``device``
    (None: the CPU) with ``backend``, so that the kernels a training step calls are compiled (numba's first use in a
    process with an empty cache: ~20-40 s) or loaded from their cache before a run's clock starts. Touches no random
    stream and no state a run keeps. -> the seconds it took."""
    import time

    import numpy as np
    import torch

    from ..camera import Camera
    from ..devices import as_device

    t0 = time.perf_counter()
    dev = as_device(device)
    u = torch.linspace(-1.0, 1.0, 64, dtype=torch.float32)
    means = torch.stack([0.8 * u, 0.6 * torch.sin(5.0 * u), 0.3 * torch.cos(3.0 * u)], 1).to(dev).requires_grad_()
    quats = torch.stack([torch.ones_like(u), 0.3 * u, 0.2 * u.flip(0), 0.1 * u], 1).to(dev).requires_grad_()
    scales = (0.02 + 0.08 * (u + 1.0)).repeat(3, 1).T.contiguous().to(dev).requires_grad_()
    opacities = (0.3 + 0.3 * (u + 1.0)).to(dev).requires_grad_()
    colors = torch.stack([(u + 1.0) / 2.0, 1.0 - (u + 1.0) / 2.0, 0.5 + 0.0 * u], 1).to(dev).requires_grad_()
    w2c = np.eye(4)
    w2c[2, 3] = 3.0  # the scene 3 units in front of the camera, along +z
    cam = Camera(w2c, 40.0, 40.0, 16.0, 16.0, 32, 32, name="warm-up")
    r = render_gaussians(means, quats, scales, opacities, colors, cam, background=(0.5, 0.5, 0.5), backend=backend)
    (r.image.sum() + r.alpha.sum()).backward()
    return time.perf_counter() - t0


__all__ = ["GateConfig", "Projected", "RenderResult", "project", "project_gaussians", "rasterize",
           "rasterize_reference", "render_gaussians", "available_backends", "resolve_backend", "warm_up",
           "BACKENDS"]


#: The largest supersampling factor ``render_supersampled`` accepts (8 x 8 renders per output pixel).
MAX_SUPERSAMPLE = 8
#: The largest side of the image ``render_supersampled`` renders before filtering (16384 px: 3.2 GB of float32 RGB at
#: 16384 x 16384, where a reference camera's 2x render at 8x would otherwise ask for more)
MAX_SUPERSAMPLED_SIDE = 16384


def check_supersample(factor) -> int:
    """``factor`` as an int in 1..``MAX_SUPERSAMPLE``, else our one-line error."""
    if isinstance(factor, bool) or not isinstance(factor, (int, float)) or factor != int(factor) \
            or not 1 <= int(factor) <= MAX_SUPERSAMPLE:
        raise ProxycodecError(f"supersampling factor must be an integer in 1..{MAX_SUPERSAMPLE}, got {factor!r}")
    return int(factor)


def render_supersampled(model, camera, xi: float, factor: int = 1, *, backend: str = "auto"):
    """``model.render(camera, xi)`` anti-aliased by supersampling (any model with ``render(camera, xi, backend=,
    size=)``: an anchor scene, a decoded container, plain 3DGS).

    ``factor`` 1 is the plain render. Otherwise the view renders at ``factor`` times the output's width and height
    (the same field of view; a resolution embedding sees ``factor * xi``, capped at ``camera.XI_MAX``) and each
    ``factor x factor`` block of pixels is averaged: a box filter, the area average the photos' smaller sizes are
    made with (``formats.images``). The result keeps the large render's ``projected`` (what was drawn there)."""
    factor = check_supersample(factor)
    if factor == 1:  # before any torch import: the torch-free decode path renders through here too
        return model.render(camera, xi, backend=backend)
    import dataclasses

    from ..camera import XI_MAX, check_xi

    small = camera.scaled(check_xi(xi))
    if max(small.width, small.height) * factor > MAX_SUPERSAMPLED_SIDE:
        raise ProxycodecError(f"supersampling {small.width}x{small.height} by {factor} renders "
                              f"{small.width * factor}x{small.height * factor} pixels, over {MAX_SUPERSAMPLED_SIDE} a "
                              "side: lower the factor or the resolution")
    r = model.render(camera, min(factor * float(xi), XI_MAX), backend=backend,
                     size=(small.width * factor, small.height * factor))

    def box(x: torch.Tensor) -> torch.Tensor:  # [H*f, W*f, C] -> [H, W, C]
        H, W, C = small.height, small.width, x.shape[-1]
        return x.reshape(H, factor, W, factor, C).mean(dim=(1, 3))

    return dataclasses.replace(r, image=box(r.image), alpha=box(r.alpha[..., None])[..., 0])
