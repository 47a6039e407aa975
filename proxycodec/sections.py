"""A scene container's sections -> numpy arrays, torch-free (every section: ``formats/CONTAINER.md``).

``codec.py`` decodes a container to a ``SceneModel`` (torch); ``proxycodec.lite`` decodes and renders one view
without importing torch. Both read the container through the functions here (dequantisation, grid positions, the
proxy split, weights with their int8 row scales, cameras), so the stored arrays come out bit for bit the same and
a malformed file fails the same way, with one ``ContainerError``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import ProxycodecError
from .formats.container import Container, ContainerError, read_container
from .netconfig import DecoderConfig, PredictorConfig

SCENE_KIND = "proxycodec.scene"
SCENE_FORMAT = 2  # version of the scene sections (inside container format 1); 2: weights packed per group and dtype
SUPPORTED_SCENE_FORMATS = (1, 2)
FLOAT_BITS = 32  # "bits" value meaning: store float32, no quantisation
PREDICT_CHUNK = 65536  # leaves per predictor batch (fixed: the same batches in encoder and decoder)
MAX_ANCHORS = 1 << 28
QSCALE = ".qscale"  # suffix of the per-row scale section of an int8 ("q8") weight matrix

ErrorFactory = Callable[[str], ProxycodecError]


# ---------------------------------------------------------------------------------------------- primitives
def _dequantize(q: np.ndarray, params: dict, name: str, err) -> np.ndarray:
    """Inverse of ``codec._quantize``: offset + q * scale in float64, rounded once to float32."""
    bits = params["bits"]
    if bits == FLOAT_BITS:
        if q.dtype != np.float32:
            raise err(f"section {name!r} must be float32")
        if not np.all(np.isfinite(q)):
            raise err(f"section {name!r} contains NaN or Inf")
        return np.array(q, dtype=np.float32)
    if not (isinstance(bits, int) and 1 <= bits <= 16):
        raise err(f"section {name!r}: bad bit depth {bits!r}")
    want = np.uint8 if bits <= 8 else np.uint16
    if q.dtype != want:
        raise err(f"section {name!r} has dtype {q.dtype}, expected {np.dtype(want)} for {bits} bits")
    off = np.asarray(params["offset"], dtype=np.float64)
    sc = np.asarray(params["scale"], dtype=np.float64)
    if off.shape != (q.shape[0],) or sc.shape != (q.shape[0],):
        raise err(f"section {name!r}: quantisation parameters do not match its {q.shape[0]} channels")
    if not (np.all(np.isfinite(off)) and np.all(np.isfinite(sc)) and np.all(sc >= 0)):
        raise err(f"section {name!r}: quantisation parameters are not finite")
    if int(q.max(initial=0)) > (1 << bits) - 1:
        raise err(f"section {name!r}: value exceeds {bits} bits")
    x = (off[:, None] + q.astype(np.float64) * sc[:, None]).astype(np.float32)
    if not np.all(np.isfinite(x)):
        raise err(f"section {name!r} dequantises to NaN or Inf")
    return x


def _grid_to_xyz(ii: np.ndarray, step: float, rule: str) -> np.ndarray:
    if rule == "f64":
        return (ii.astype(np.float64) * step).astype(np.float32)
    return ii.astype(np.float32) * np.float32(step)


def _section(sections, name, err, shape=None, kinds="f") -> np.ndarray:
    if name not in sections:
        raise err(f"missing section {name!r}")
    a = sections[name]
    if shape is not None and tuple(a.shape) != tuple(shape):
        raise err(f"section {name!r} has shape {tuple(a.shape)}, expected {tuple(shape)}")
    if a.dtype.kind not in kinds:
        raise err(f"section {name!r} has unexpected dtype {a.dtype}")
    return a


def _weights_from_sections(prefix, sections, err) -> dict[str, np.ndarray]:
    out = {}
    for k, v in sections.items():
        if not k.startswith(prefix + "/") or k.endswith(QSCALE):
            continue
        if v.dtype == np.int8:
            scale = sections.get(k + QSCALE)
            if scale is None or scale.dtype != np.float32 or v.ndim != 2 or scale.shape != (v.shape[0],):
                raise err(f"section {k!r}: int8 weights need a float32 per-row scale section")
            if not np.all(np.isfinite(scale)):
                raise err(f"section {k!r}: weight scales are not finite")
            out[k[len(prefix) + 1:]] = (v.astype(np.float32) * scale[:, None]).astype(np.float32)
        elif v.dtype in (np.float16, np.float32):
            out[k[len(prefix) + 1:]] = v.astype(np.float32)
        else:
            raise err(f"section {k!r}: weights must be float16, float32 or int8 (with scales)")
    return out


# ---------------------------------------------------------------------------------------------- weight packing
WEIGHT_GROUPS = ("decoder", "predictor")
PACKED_DTYPES = ("i1", "f2", "f4")  # int8 matrices, float16 vectors (or f16 weights), float32 row scales/weights
MAX_WEIGHT_VALUES = 1 << 26


def _packed_name(group: str, code: str) -> str:
    return f"{group}/packed.{code}"


def pack_weights(sections: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], list]:
    """Scene format 2: the weight sections (``decoder/*``, ``predictor/*``, int8 row scales included) concatenated
    per group and dtype into 1-D sections ``<group>/packed.<i1|f2|f4>``, in their order; returns the new sections
    and the layout ``[[name, dtype code, shape], ...]`` the metadata keeps (``weights_layout``). Fifty-odd small
    sections cost ~80 B of table entry and ~10 B of zstd frame each; six cost a tenth of that."""
    out: dict[str, np.ndarray] = {}
    layout: list = []
    parts: dict[str, list[np.ndarray]] = {}
    for k, v in sections.items():
        group = k.split("/")[0]
        if group not in WEIGHT_GROUPS:
            out[k] = v
            continue
        code = np.dtype(v.dtype).str[1:]
        if code not in PACKED_DTYPES:
            raise ProxycodecError(f"weight section {k!r} has dtype {v.dtype}, which cannot be packed")
        layout.append([k, code, [int(n) for n in v.shape]])
        parts.setdefault(_packed_name(group, code), []).append(np.ascontiguousarray(v).ravel())
    for name, ps in parts.items():
        out[name] = np.concatenate(ps)
    return out, layout


def unpack_weights(meta: dict, arrays: dict[str, np.ndarray], err: ErrorFactory) -> dict[str, np.ndarray]:
    """Inverse of ``pack_weights`` for a scene-format-2 container (format 1 is returned as it is). Every entry of
    the layout is checked (name, dtype, shape) and the packed sections must be consumed exactly."""
    if meta.get("scene_format") == 1:
        return dict(arrays)
    layout = meta.get("weights_layout")
    if not isinstance(layout, list) or len(layout) > 4096:
        raise err("weights_layout is missing or not a list")
    out = {k: v for k, v in arrays.items() if k.split("/")[0] not in WEIGHT_GROUPS}
    used: dict[str, int] = {}
    for entry in layout:
        if not (isinstance(entry, list) and len(entry) == 3 and isinstance(entry[0], str)
                and entry[1] in PACKED_DTYPES and isinstance(entry[2], list) and len(entry[2]) <= 2
                and all(isinstance(n, int) and not isinstance(n, bool) and 0 <= n <= MAX_WEIGHT_VALUES
                        for n in entry[2])):
            raise err(f"bad weights_layout entry {str(entry)[:80]!r}")
        name, code, shape = entry
        group = name.split("/")[0]
        if group not in WEIGHT_GROUPS or name in out:
            raise err(f"bad or repeated weight name {name[:80]!r} in weights_layout")
        src = _packed_name(group, code)
        packed = arrays.get(src)
        if packed is None or packed.ndim != 1 or packed.dtype != np.dtype("<" + code):
            raise err(f"missing or malformed section {src!r}")
        n = math.prod(shape)
        start = used.get(src, 0)
        if start + n > packed.size:
            raise err(f"section {src!r} is shorter than weights_layout says")
        out[name] = packed[start:start + n].reshape(shape)
        used[src] = start + n
    for k, v in arrays.items():
        if k.split("/")[0] in WEIGHT_GROUPS and used.get(k) != v.size:
            raise err(f"section {k!r} does not match weights_layout")
    return out


# ---------------------------------------------------------------------------------------------- reading
def read_scene_container(path: str | os.PathLike) -> Container:
    """Read and verify a scene container (raises ``ContainerError``): CRCs, kind and scene format. The arrays come
    back as scene format 1 names them (format 2's packed weights unpacked)."""
    path = Path(path)
    c = read_container(path)
    if c.meta.get("kind") != SCENE_KIND:
        raise ContainerError(f"not a compressed scene (kind {c.meta.get('kind')!r})", path)
    fmt = c.meta.get("scene_format")
    if fmt not in SUPPORTED_SCENE_FORMATS:
        raise ContainerError(f"scene format {fmt!r} is not supported by this proxycodec (supports "
                             f"{', '.join(map(str, SUPPORTED_SCENE_FORMATS))}); upgrade proxycodec", path)

    def err(m: str) -> ContainerError:
        return ContainerError(m, path)

    return replace(c, arrays=unpack_weights(c.meta, c.arrays, err))


def guarded(fn, err: ErrorFactory, *args):
    """``fn(*args)``, with malformed metadata (a missing key, a wrong type...) and a ``ProxycodecError`` raised
    while building the scene turned into one ``err`` error (a ``ContainerError`` naming the file, when reading)."""
    try:
        return fn(*args)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError) as e:
        if isinstance(e, ProxycodecError):
            if isinstance(e, ContainerError) or not isinstance(err(""), ContainerError):
                raise
            raise err(e.reason) from None
        raise err(f"bad scene metadata ({type(e).__name__}: {e})") from None


@dataclass
class StoredAnchors:
    """What a scene container stores, dequantised, in the stored (Morton) order; leaves not yet regenerated."""

    positions: np.ndarray  # [M, 3] float32
    features: np.ndarray  # [M, F] float32: the proxies' rows; the leaves' rows are zero
    offsets: np.ndarray  # [M, K, 3] float32 (leaves' rows zero when they are predicted)
    scalings: np.ndarray  # [M, 6] float32, log space
    proxy_mask: np.ndarray  # [M] bool
    voxel_size: float
    decoder_config: DecoderConfig
    predictor_config: PredictorConfig


def stored_anchors(meta: dict, sections: dict[str, np.ndarray], err: ErrorFactory) -> StoredAnchors:
    """The stored arrays and the network configurations, checked against each other (no ``guarded`` here)."""
    a = meta["anchors"]
    M, P, Fd, K = (int(a[k]) for k in ("count", "proxies", "feat_dim", "n_offsets"))
    if not (0 < M <= MAX_ANCHORS and 0 < P <= M and a["leaves"] == M - P and 0 < Fd <= 4096 and 0 < K <= 4096):
        raise err(f"bad anchor counts {a}")
    voxel = float(meta["voxel_size"])
    if not (math.isfinite(voxel) and voxel > 0):
        raise err(f"bad voxel size {voxel}")
    # positions
    pinfo = meta["positions"]
    if pinfo["mode"] == "grid":
        d = _section(sections, "anchors/grid", err, (3, M), "i").astype(np.int64)
        rel = np.cumsum(d, axis=1).T
        origin = np.asarray([int(v) for v in pinfo["origin"]], dtype=np.int64)
        if origin.shape != (3,):
            raise err("bad grid origin")
        ii = rel + origin
        if len(ii) and np.abs(ii).max() >= 2**31:
            raise err("grid coordinates out of range")
        step = float(pinfo["step"])
        if not (math.isfinite(step) and step > 0) or pinfo["rule"] not in ("f64", "f32"):
            raise err("bad grid step or rule")
        pos = _grid_to_xyz(ii, step, pinfo["rule"])
    elif pinfo["mode"] == "float32":
        pos = np.ascontiguousarray(_section(sections, "anchors/xyz", err, (3, M)).T)
        if pos.dtype != np.float32 or not np.all(np.isfinite(pos)):
            raise err("section 'anchors/xyz' must hold finite float32 values")
    else:
        raise err(f"unknown position mode {pinfo['mode']!r}")
    if not np.all(np.isfinite(pos)):
        raise err("positions are not finite")
    # split
    bits = _section(sections, "anchors/proxy_mask", err, ((M + 7) // 8,), "u")
    mask = np.unpackbits(bits, count=M, bitorder="little").astype(bool)
    if int(mask.sum()) != P:
        raise err(f"proxy mask marks {int(mask.sum())} proxies, metadata says {P}")
    q = meta["quant"]
    scal = _dequantize(_section(sections, "anchors/scalings", err, (6, M), "uf"), q["scalings"],
                       "anchors/scalings", err).T
    feats = np.zeros((M, Fd), dtype=np.float32)
    feats[mask] = _dequantize(_section(sections, "proxy/features", err, (Fd, P), "uf"), q["features"],
                              "proxy/features", err).T
    offsets_mode = meta["offsets"]
    if offsets_mode == "stored":
        offs = _dequantize(_section(sections, "anchors/offsets", err, (3 * K, M), "uf"), q["offsets"],
                           "anchors/offsets", err).T.reshape(M, K, 3)
    elif offsets_mode == "predicted":
        offs = np.zeros((M, K, 3), dtype=np.float32)
        offs[mask] = _dequantize(_section(sections, "proxy/offsets", err, (3 * K, P), "uf"), q["offsets"],
                                 "proxy/offsets", err).T.reshape(P, K, 3)
    else:
        raise err(f"unknown offsets mode {offsets_mode!r}")
    # networks
    dcfg = DecoderConfig.from_json(meta["decoder"])
    pcfg = PredictorConfig.from_json(meta["predictor"])
    if (dcfg.feat_dim, dcfg.n_offsets, pcfg.feat_dim, pcfg.n_offsets) != (Fd, K, Fd, K):
        raise err("network configurations do not match the anchors' feature/offset sizes")
    if pcfg.predict_offsets != (offsets_mode == "predicted"):
        raise err("predictor configuration disagrees with the offsets mode")
    return StoredAnchors(pos, feats, offs, np.ascontiguousarray(scal), mask, voxel, dcfg, pcfg)


def scene_extras(meta: dict, proxy_mask: np.ndarray, err: ErrorFactory) -> tuple[list[Camera], tuple, dict]:
    """(stored cameras, background, the scene's metadata with ``proxy_mask`` added)."""
    cams = [Camera.from_json(c) for c in meta.get("cameras", [])]
    bg = tuple(float(x) for x in meta.get("background", (1.0, 1.0, 1.0)))
    if len(bg) != 3:
        raise err("background must have 3 components")
    scene_meta = dict(meta.get("scene", {})) if isinstance(meta.get("scene", {}), dict) else {}
    scene_meta["proxy_mask"] = proxy_mask  # which anchors were proxies (in the stored order)
    return cams, bg, scene_meta
