"""Anchor features at arbitrary 3D points (supplement section 8.1): what an anchor that formed at a point would hold.

For each query point q: its nearest proxies among the scene's proxies (``nearest.predictor_neighbours``, the
decoder's search under the predictor's tie rule; as many as the predictor's ``context``; under "grid" q is rounded
to the lattice of 1/16 voxel for the search, which a leaf's position already lies on), then the residual
predictor as it regenerates a leaf (``f~_q = f_k + delta_f(f_k, PE(log |q - v_k|), PE(unit(q - v_k)))``), then the
resolution embedding at xi (``GaussianDecoder.embed``: FiLM ``(1 + gamma) f + beta`` at q's position). So at a leaf
anchor's own position the query gives that leaf's decoded feature, embedded as the renderer embeds it.

[D] At a proxy's own position (distance 0 to its nearest proxy) the anchor that formed there is the proxy: the query
gives its stored feature (embedded), so querying every anchor position reproduces the decoded scene's embedded
features. ``exact_proxies=False`` gives the predictor's answer there instead, for a zero offset (distance clamped to
1e-6 ``dist_ref``, direction 0), which is not the stored feature unless the predictor's correction vanishes.

Points are rounded to float32, as anchor positions are.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .camera import check_xi
from .devices import as_device
from .errors import ProxycodecError
from .formats.container import MAGIC
from .model import SceneModel, weights_path_for
from .nearest import predictor_neighbours
from .sections import PREDICT_CHUNK

__all__ = ["FeatureField", "query_features"]


def _check_points(points) -> np.ndarray:
    """[N, 3] finite float32 points, or one ``ProxycodecError`` line."""
    if isinstance(points, torch.Tensor):
        points = points.detach().cpu().numpy()
    try:
        p = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ProxycodecError(f"points must be an [N, 3] array of numbers ({type(e).__name__}: "
                              f"{str(e).splitlines()[0][:80]})") from None
    if p.ndim != 2 or p.shape[1] != 3:
        raise ProxycodecError(f"points must be an [N, 3] array, got shape {p.shape}")
    bad = ~np.isfinite(p).all(1)
    if bad.any():
        raise ProxycodecError(f"points hold NaN or infinity ({int(bad.sum())} of {len(p)} rows, first row "
                              f"{int(np.flatnonzero(bad)[0])})")
    if len(p) and np.abs(p).max() > np.finfo(np.float32).max:
        raise ProxycodecError("points are out of float32 range")
    return p.astype(np.float32)


@dataclass
class FeatureField:
    """The scene's proxies, predictor and decoder, ready to answer :meth:`query` for any points.

    ``FeatureField.open(source)`` takes a container path, an anchor PLY whose weights sidecar holds a stage-2
    predictor (``proxycodec fit``), a ``codec.CompressedScene``, or a ``SceneModel`` with ``predictor=`` (and the
    proxy mask as ``proxy_mask=`` or in ``scene.metadata["proxy_mask"]``, where ``decode`` puts it)."""

    proxy_positions: torch.Tensor  # [P, 3] float32
    proxy_features: torch.Tensor  # [P, F]
    proxy_offsets: torch.Tensor  # [P, K, 3]
    predictor: torch.nn.Module
    decoder: torch.nn.Module
    bounds: np.ndarray  # [2, 3] axis-aligned bounds of all the scene's anchors (proxies and leaves)
    voxel_size: float
    source: str = ""

    @classmethod
    def open(cls, source, *, predictor=None, proxy_mask=None, device=None) -> FeatureField:
        from . import codec

        name = ""
        if isinstance(source, (str, os.PathLike)):
            name = str(source)
            p = Path(source)
            if not p.is_file():
                raise ProxycodecError("no such file" if not p.exists() else "is not a file", p)
            with p.open("rb") as fh:
                is_container = fh.read(len(MAGIC)) == MAGIC
            if is_container:
                source = codec.load(p)
            else:
                from .proxy import load_fitted_predictor

                model = SceneModel.load(p)
                if predictor is None:
                    predictor, fitted_mask = load_fitted_predictor(weights_path_for(p))
                    if predictor is None:
                        raise ProxycodecError("has no stage-2 residual predictor in its weights sidecar (fit it with "
                                              "proxies, or encode it and query the container)", p)
                    proxy_mask = fitted_mask if proxy_mask is None else proxy_mask
                source = model
        if isinstance(source, codec.CompressedScene):
            name = name or str(source.path)
            predictor = predictor or source.predictor()
            source = source.to_model()
        if not isinstance(source, SceneModel):
            raise ProxycodecError(f"query_features takes a container or anchor PLY path, a CompressedScene or a "
                                  f"SceneModel, not {type(source).__name__}")
        if predictor is None:
            raise ProxycodecError("a SceneModel needs its residual predictor (predictor=...) to be queried")
        s = source.scene
        mask = proxy_mask if proxy_mask is not None else s.metadata.get("proxy_mask")
        if mask is None:
            raise ProxycodecError("the scene does not say which anchors are proxies (proxy_mask=...)")
        mask = np.asarray(mask)
        if mask.shape != (s.num_anchors,) or mask.dtype != bool or not mask.any():
            raise ProxycodecError(f"the proxy mask must be [{s.num_anchors}] booleans with at least one proxy, got "
                                  f"{mask.dtype} {mask.shape}")
        idx = torch.from_numpy(np.flatnonzero(mask)).to(s.positions.device)
        dev = s.positions.device if device is None else as_device(device)
        return cls(s.positions.detach()[idx].float().to(dev), s.features.detach()[idx].float().to(dev),
                   s.offsets.detach()[idx].float().to(dev), predictor.eval().to(dev), source.decoder.eval().to(dev),
                   s.bounds(), float(s.voxel_size), name)

    @property
    def device(self) -> torch.device:
        return self.proxy_positions.device

    @property
    def feat_dim(self) -> int:
        return int(self.proxy_features.shape[1])

    def predict(self, points, exact_proxies: bool = True) -> np.ndarray:
        """[N, F] predicted features at ``points`` before the resolution embedding (xi-independent)."""
        from .proxy import torch_threads

        dev = self.device
        q = torch.from_numpy(_check_points(points)).to(dev)
        P, N = self.proxy_positions.shape[0], q.shape[0]
        out = torch.empty(N, self.feat_dim, device=dev)
        if N == 0:
            return out.cpu().numpy()
        pos = torch.cat([self.proxy_positions, q])
        feats = torch.cat([self.proxy_features, self.proxy_features.new_zeros(N, self.feat_dim)])
        offs = torch.cat([self.proxy_offsets, self.proxy_offsets.new_zeros((N,) + tuple(self.proxy_offsets.shape[1:]))])
        pcfg = getattr(self.predictor, "config", None)
        mask = np.zeros(P + N, dtype=bool)
        mask[:P] = True  # the proxies, in their stored order: ties go to the same proxy as in decoding
        nearest = torch.from_numpy(predictor_neighbours(pos.cpu().numpy(), mask, pcfg)).to(dev)
        with torch.no_grad(), torch_threads(1):  # fixed thread count, as the decoder regenerates leaves
            for s in range(0, N, PREDICT_CHUNK):
                rows = torch.arange(P + s, P + min(N, s + PREDICT_CHUNK), device=dev)
                out[s:s + len(rows)] = self.predictor.predict(pos, feats, nearest, rows, offs)[0]
        if exact_proxies:
            near = nearest[P:, 0]
            at = (pos[P:] == pos[near]).all(1)
            out[at] = self.proxy_features[near[at]]
        return out.cpu().numpy()

    def embed(self, points, features, xi: float) -> np.ndarray:
        """The resolution embedding (FiLM) at ``xi`` of ``features`` [N, F] located at ``points``."""
        xi = check_xi(xi)
        q = torch.from_numpy(_check_points(points)).to(self.device)
        f = torch.as_tensor(np.asarray(features, dtype=np.float32), device=self.device)
        if f.shape != (q.shape[0], self.feat_dim):
            raise ProxycodecError(f"features must be [{q.shape[0]}, {self.feat_dim}], got {tuple(f.shape)}")
        with torch.no_grad():
            return self.decoder.embed(q, f, xi).cpu().numpy()

    def query(self, points, xi: float, exact_proxies: bool = True) -> np.ndarray:
        """[N, F] float32: the features an anchor at each point would have, embedded at resolution ratio ``xi``."""
        check_xi(xi)
        return self.embed(points, self.predict(points, exact_proxies), xi)


def query_features(scene_or_container, points, xi: float, *, predictor=None, proxy_mask=None,
                   exact_proxies: bool = True, device=None) -> np.ndarray:
    """[N, F] float32 anchor features predicted at ``points`` ([N, 3]) and embedded at resolution ratio ``xi``: nearest
    proxies + residual predictor + FiLM (module docstring). ``scene_or_container``: see :class:`FeatureField`.
    ``device``: where the predictor and the embedding run (None: where the scene lies; files load on the CPU)."""
    field = FeatureField.open(scene_or_container, predictor=predictor, proxy_mask=proxy_mask, device=device)
    return field.query(points, xi, exact_proxies)
