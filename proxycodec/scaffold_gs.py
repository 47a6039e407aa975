"""A trained Scaffold-GS output (city-super/Scaffold-GS) as a renderable ``SceneModel``, read without running it.

What Scaffold-GS writes (``Scene.save``, ``GaussianModel.save_mlp_checkpoints``), and what is read here:

- ``point_cloud/iteration_<N>/point_cloud.ply``: the anchors (``formats/scaffold_ply.py``); the largest N is used.
- beside it, the MLPs: ``opacity_mlp.pt``, ``cov_mlp.pt``, ``color_mlp.pt`` (+ ``feature_bank_mlp.pt`` with
  ``use_feat_bank``, ``embedding_appearance.pt`` with ``appearance_dim > 0``), TorchScript archives of
  ``torch.jit.trace`` (mode "split", the default), or one ``checkpoints.pth`` of state dicts (mode "unite"). Their
  tensors are read by ``formats/torchscript.py``: no code in them runs, nothing but tensors is unpickled.
- in the output folder: ``cameras.json`` (the views, 3DGS's ``camera_to_JSON``) and ``cfg_args`` (the run's
  ``Namespace(...)``, parsed with ``ast`` literals only: voxel size, white background, and cross-checks).

The decoder is ours (``GaussianDecoder``) with Scaffold-GS's variant recorded in its configuration (distance inputs
per MLP, feature bank) and its weights; the FiLM resolution embedding is added at the identity (last layer zero), the
coverage gate on with its defaults, so at xi = 1 with the gate off a render decodes exactly the Gaussians Scaffold-GS's
``generate_neural_gaussians`` does. An appearance embedding (per training camera) is folded into the colour MLP's
first bias with one fixed row (``appearance_row``, default 0): our renderer has no camera identity.
"""

from __future__ import annotations

import ast
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import ProxycodecError
from .formats.torchscript import ScriptObject, read_torch_checkpoint, read_torchscript

__all__ = ["ScaffoldFiles", "is_scaffold_output", "find_scaffold_files", "load_scaffold_output",
           "read_cfg_args", "read_scaffold_cameras", "find_beside", "find_cameras_json", "write_cameras_json", "SPLIT_FILES",
           "CHECKPOINT_FILE"]

#: Mode "split": one TorchScript archive per network (Scaffold-GS's file names).
SPLIT_FILES = {"opacity": "opacity_mlp.pt", "cov": "cov_mlp.pt", "color": "color_mlp.pt",
               "bank": "feature_bank_mlp.pt", "appearance": "embedding_appearance.pt"}
#: Mode "unite": one ``torch.save`` of state dicts, under these keys (the first is Scaffold-GS's).
CHECKPOINT_FILE = "checkpoints.pth"
UNITE_KEYS = {"opacity": ("opacity_mlp",), "cov": ("cov_mlp",), "color": ("color_mlp",),
              "bank": ("feature_bank_mlp", "mlp_feature_bank"), "appearance": ("appearance", "embedding_appearance")}
PLY_NAME = "point_cloud.ply"
MAX_TEXT_BYTES = 64 << 20
_ITERATION = re.compile(r"iteration_(\d{1,12})")
#: Each network's layers after its first Linear's ReLU and second Linear (Scaffold-GS's ``nn.Sequential``s).
_HEADS = {"opacity": "Tanh", "cov": None, "color": "Sigmoid", "bank": "Softmax"}


# ---------------------------------------------------------------------------------------------- finding the files
@dataclass(frozen=True)
class ScaffoldFiles:
    """Where a Scaffold-GS output's parts are (``find_scaffold_files``)."""

    ply: Path
    mlp_dir: Path  # the PLY's folder: the MLP files sit beside it
    mode: str | None  # "split" | "unite" | None (no MLP file found)
    output_dir: Path  # the run's folder (cameras.json, cfg_args)
    iteration: int | None

    @property
    def cameras_json(self) -> Path | None:
        p = self.output_dir / "cameras.json"
        return p if p.is_file() else None

    @property
    def cfg_args(self) -> Path | None:
        p = self.output_dir / "cfg_args"
        return p if p.is_file() else None

    def mlp_files(self) -> list[Path]:
        """The MLP files of this output that exist (what is read)."""
        if self.mode == "unite":
            return [self.mlp_dir / CHECKPOINT_FILE]
        return [self.mlp_dir / n for n in SPLIT_FILES.values() if (self.mlp_dir / n).is_file()]


def _mode(folder: Path) -> str | None:
    if (folder / SPLIT_FILES["opacity"]).is_file():
        return "split"  # Scaffold-GS's default (load_mlp_checkpoints(mode='split'))
    if (folder / CHECKPOINT_FILE).is_file():
        return "unite"
    return None


def _output_dir(ply_dir: Path) -> Path:
    """``<out>/point_cloud/iteration_N`` -> ``<out>``; any other folder is its own output folder."""
    if _ITERATION.fullmatch(ply_dir.name) and ply_dir.parent.name == "point_cloud":
        return ply_dir.parent.parent
    return ply_dir


def _latest_iteration(out: Path) -> tuple[Path, int] | None:
    best = None
    try:
        entries = list((out / "point_cloud").iterdir())
    except OSError:
        return None
    for d in entries:
        m = _ITERATION.fullmatch(d.name)
        if m and (d / PLY_NAME).is_file() and (best is None or int(m.group(1)) > best[1]):
            best = (d, int(m.group(1)))
    return best


def find_scaffold_files(path: str | os.PathLike) -> ScaffoldFiles | None:
    """The parts of the Scaffold-GS output at ``path`` (its folder, a ``point_cloud/iteration_N`` folder, or the
    PLY), or None when ``path`` is not one. A PLY counts only with Scaffold-GS's MLP files beside it and without a
    proxycodec weights sidecar (``X.weights.pxc``, which then wins: a scene of ours)."""
    p = Path(path)
    try:
        if p.is_dir():
            if (p / PLY_NAME).is_file():
                ply_dir, it = p, None
                m = _ITERATION.fullmatch(p.name)
                it = int(m.group(1)) if m else None
            else:
                found = _latest_iteration(p)
                if found is None:
                    return None
                ply_dir, it = found
            return ScaffoldFiles(ply_dir / PLY_NAME, ply_dir, _mode(ply_dir), _output_dir(ply_dir), it)
        if p.is_file() and p.suffix.lower() == ".ply":
            from .model import weights_path_for

            mode = _mode(p.parent)
            if mode is None or weights_path_for(p).exists():
                return None
            m = _ITERATION.fullmatch(p.parent.name)
            return ScaffoldFiles(p, p.parent, mode, _output_dir(p.parent), int(m.group(1)) if m else None)
    except OSError:
        return None
    return None


def is_scaffold_output(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a Scaffold-GS output (folder or PLY with its MLP files; ``find_scaffold_files``)."""
    return find_scaffold_files(path) is not None


# ---------------------------------------------------------------------------------------------- cfg_args, cameras
def _read_text(path: Path) -> str:
    try:
        size = path.stat().st_size
        if size > MAX_TEXT_BYTES:
            raise ProxycodecError(f"{size:,} B is too large (at most {MAX_TEXT_BYTES:,} B)", path)
        return path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise ProxycodecError("is not UTF-8 text", path) from None
    except OSError as e:
        raise ProxycodecError(f"cannot read it ({e.strerror})", path) from None


def read_cfg_args(path: str | os.PathLike) -> dict:
    """Scaffold-GS's ``cfg_args`` (``str(Namespace(...))``) as a dict of its literal values, without ``eval``:
    the text is parsed with ``ast`` and each keyword's value with ``ast.literal_eval``; values that are not
    literals are left out."""
    path = Path(path)
    text = _read_text(path)
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except (SyntaxError, ValueError, RecursionError, MemoryError) as e:
        raise ProxycodecError(f"not a Namespace(...) line ({type(e).__name__})", path) from None
    call = tree.body
    if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name) and call.func.id == "Namespace"
            and not call.args):
        raise ProxycodecError("not a Namespace(...) line", path)
    out = {}
    for kw in call.keywords:
        if kw.arg is None:
            raise ProxycodecError("Namespace(**...) is not a literal", path)
        try:
            out[kw.arg] = ast.literal_eval(kw.value)
        except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError):
            continue
    return out


def _number(v, what: str, path: Path, integer: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or (integer and not isinstance(v, int)) \
            or not math.isfinite(v):
        raise ProxycodecError(f"{what} must be a finite {'integer' if integer else 'number'}, got {str(v)[:40]!r}",
                              path)
    return v


def read_scaffold_cameras(path: str | os.PathLike) -> list[Camera]:
    """The views of Scaffold-GS's / 3DGS's ``cameras.json``: per view ``position`` (the camera centre) and
    ``rotation`` (camera-to-world rotation, OpenCV axes), ``fx``, ``fy``, ``width``, ``height``; the principal point
    is the image centre, as 3DGS's projection assumes."""
    path = Path(path)
    try:
        data = json.loads(_read_text(path))
    except (ValueError, RecursionError) as e:
        raise ProxycodecError(f"not valid JSON ({type(e).__name__})", path) from None
    if not isinstance(data, list) or not data:
        raise ProxycodecError("cameras.json must hold a non-empty list of views", path)
    cams = []
    for i, d in enumerate(data):
        if not isinstance(d, dict):
            raise ProxycodecError(f"view {i} is not a JSON object", path)
        try:
            pos = np.array(d["position"], dtype=np.float64)
            rot = np.array(d["rotation"], dtype=np.float64)
            w, h = (int(_number(d[k], f"view {i} {k}", path, True)) for k in ("width", "height"))
            fx, fy = (float(_number(d[k], f"view {i} {k}", path)) for k in ("fx", "fy"))
        except KeyError as e:
            raise ProxycodecError(f"view {i} lacks {e.args[0]!r}", path) from None
        except (TypeError, ValueError, OverflowError):
            raise ProxycodecError(f"view {i}: position must be 3 numbers and rotation 3x3", path) from None
        if not (1 <= w <= 1 << 20 and 1 <= h <= 1 << 20):  # COLMAP's reader's bound
            raise ProxycodecError(f"view {i} has an implausible size {w}x{h}", path)
        if pos.shape != (3,) or rot.shape != (3, 3) or not (np.isfinite(pos).all() and np.isfinite(rot).all()):
            raise ProxycodecError(f"view {i}: position must be 3 finite numbers and rotation a finite 3x3", path)
        if abs(np.linalg.det(rot) - 1.0) > 1e-3 or not np.allclose(rot.T @ rot, np.eye(3), atol=1e-3):
            raise ProxycodecError(f"view {i}: rotation is not a rotation matrix", path)
        w2c = np.eye(4)
        w2c[:3, :3] = rot.T
        w2c[:3, 3] = -rot.T @ pos
        name = str(d.get("img_name", f"view_{i:03d}"))[:200]
        try:
            cams.append(Camera(w2c, fx, fy, w / 2.0, h / 2.0, w, h, name=name))
        except ProxycodecError as e:
            raise ProxycodecError(f"view {i}: {e.reason}", path) from None
    return cams


def find_beside(ply_path: str | os.PathLike, name: str) -> Path | None:
    """The file ``name`` beside the PLY, or two folders up (3DGS's ``OUT/point_cloud/iteration_N/point_cloud.ply``
    with ``OUT/cameras.json`` and ``OUT/cfg_args``); for a symbolic link, around the link first, then around the file
    it points to."""
    link = Path(os.path.abspath(ply_path)).parent
    real = Path(ply_path).resolve().parent
    for folder in (link, link.parent.parent, real, real.parent.parent):
        c = folder / name
        if c.is_file():
            return c
    return None


def find_cameras_json(ply_path: str | os.PathLike) -> Path | None:
    """``cameras.json`` found as ``find_beside`` finds files."""
    return find_beside(ply_path, "cameras.json")


def write_cameras_json(path: str | os.PathLike, cameras: list[Camera]) -> None:
    """3DGS's ``cameras.json`` (``utils/camera_utils.camera_to_JSON``): id, img_name, width, height, position (the
    centre), rotation (camera-to-world), fy, fx. Written atomically."""
    import json

    from .fileio import atomic_write

    rows = []
    for i, c in enumerate(cameras):
        rows.append({"id": i, "img_name": c.name or f"view_{i:03d}", "width": int(c.width), "height": int(c.height),
                     "position": [float(x) for x in c.center],
                     "rotation": [[float(x) for x in r] for r in np.asarray(c.rotation).T],
                     "fy": float(c.fy), "fx": float(c.fx)})
    with atomic_write(path, "w") as fh:
        json.dump(rows, fh)


# ---------------------------------------------------------------------------------------------- the networks
@dataclass
class _Net:
    """One Scaffold-GS MLP: its Linear layers (weight [out, in], bias [out]) and its layer kinds as saved."""

    linears: list[tuple[np.ndarray, np.ndarray]]
    kinds: list[str] | None  # "Linear", "ReLU", "Tanh", ... (None: a state dict, which does not record them)
    source: Path

    @property
    def n_in(self) -> int:
        return int(self.linears[0][0].shape[1])

    @property
    def hidden(self) -> int:
        return int(self.linears[0][0].shape[0])

    @property
    def n_out(self) -> int:
        return int(self.linears[-1][0].shape[0])


def _float_array(a, what: str, path: Path) -> np.ndarray:
    if not isinstance(a, np.ndarray) or a.dtype.kind != "f":
        raise ProxycodecError(f"{what} is not a floating-point tensor", path)
    out = a.astype(np.float32)
    if not np.isfinite(out).all():
        raise ProxycodecError(f"{what} holds NaN or Inf", path)
    return out


def _net_from_script(root: ScriptObject, what: str, path: Path) -> _Net:
    if not root.kind.endswith("Sequential"):
        raise ProxycodecError(f"the {what} network is a {root.kind or root.qualname}, not Scaffold-GS's "
                              "nn.Sequential", path)
    children = {k: v for k, v in root.attributes.items() if isinstance(v, ScriptObject)}
    if sorted(children) != [str(i) for i in range(len(children))]:
        raise ProxycodecError(f"the {what} network's layers are not numbered 0..n-1", path)
    linears, kinds = [], []
    for i in range(len(children)):
        layer = children[str(i)]
        kind = layer.kind.rsplit(".", 1)[-1]
        kinds.append(kind)
        if kind == "Linear":
            w, b = layer.attributes.get("weight"), layer.attributes.get("bias")
            if b is None:
                raise ProxycodecError(f"the {what} network's layer {i} is a Linear without bias", path)
            linears.append((_float_array(w, f"{what} layer {i} weight", path),
                            _float_array(b, f"{what} layer {i} bias", path)))
    return _Net(linears, kinds, path)


def _net_from_state(state, what: str, path: Path) -> _Net:
    if not isinstance(state, dict) or set(state) != {"0.weight", "0.bias", "2.weight", "2.bias"}:
        keys = sorted(state)[:6] if isinstance(state, dict) else type(state).__name__
        raise ProxycodecError(f"the {what} network's state dict has keys {keys}, not Scaffold-GS's "
                              "0.weight/0.bias/2.weight/2.bias", path)
    return _Net([(_float_array(state[f"{i}.weight"], f"{what} {i}.weight", path),
                  _float_array(state[f"{i}.bias"], f"{what} {i}.bias", path)) for i in (0, 2)], None, path)


def _check_net(net: _Net, what: str, n_out: int) -> _Net:
    """Scaffold-GS's shape: Linear(n_in, h), ReLU, Linear(h, n_out)[, its head activation]."""
    head = _HEADS[what]
    want = ["Linear", "ReLU", "Linear"] + ([head] if head else [])
    if net.kinds is not None and net.kinds != want:
        raise ProxycodecError(f"the {what} network's layers are {net.kinds}; Scaffold-GS's are {want} "
                              "(this variant cannot be represented)", net.source)
    if len(net.linears) != 2:
        raise ProxycodecError(f"the {what} network has {len(net.linears)} Linear layers, not 2", net.source)
    (w1, b1), (w2, b2) = net.linears
    if not (w1.ndim == 2 and b1.shape == (w1.shape[0],) and w2.ndim == 2 and w2.shape[1] == w1.shape[0]
            and b2.shape == (w2.shape[0],)):
        raise ProxycodecError(f"the {what} network's weight shapes do not chain "
                              f"({w1.shape}, {b1.shape}, {w2.shape}, {b2.shape})", net.source)
    if w2.shape[0] != n_out:
        raise ProxycodecError(f"the {what} network has {w2.shape[0]} outputs; the anchors need {n_out}",
                              net.source)
    return net


def _embedding_table(obj, path: Path) -> np.ndarray:
    """The [cameras, width] table of Scaffold-GS's appearance ``Embedding`` (a module or its state dict)."""
    if isinstance(obj, ScriptObject):
        inner = obj.attributes.get("embedding") if not obj.kind.endswith("sparse.Embedding") else obj
        w = inner.attributes.get("weight") if isinstance(inner, ScriptObject) else None
    elif isinstance(obj, dict):
        w = obj.get("embedding.weight", obj.get("weight"))
    else:
        w = None
    if w is None:
        raise ProxycodecError("the appearance embedding holds no embedding.weight table", path)
    w = _float_array(w, "appearance embedding", path)
    if w.ndim != 2 or w.shape[0] < 1 or w.shape[1] < 1:
        raise ProxycodecError(f"the appearance embedding table has shape {w.shape}", path)
    return w


def _read_networks(files: ScaffoldFiles) -> tuple[dict[str, _Net], np.ndarray | None]:
    d = files.mlp_dir
    nets: dict[str, _Net] = {}
    table = None
    if files.mode is None:
        raise ProxycodecError(f"no Scaffold-GS MLP files beside {files.ply.name} (expected "
                              f"{', '.join(SPLIT_FILES[k] for k in ('opacity', 'cov', 'color'))} or "
                              f"{CHECKPOINT_FILE})", d)
    if files.mode == "split":
        for what in ("opacity", "cov", "color", "bank"):
            p = d / SPLIT_FILES[what]
            if not p.is_file():
                if what == "bank":
                    continue
                raise ProxycodecError(f"missing ({SPLIT_FILES['opacity']} is there: Scaffold-GS's split MLP files "
                                      f"are {', '.join(SPLIT_FILES[k] for k in ('opacity', 'cov', 'color'))})", p)
            nets[what] = _net_from_script(read_torchscript(p), what, p)
        p = d / SPLIT_FILES["appearance"]
        if p.is_file():
            table = _embedding_table(read_torchscript(p), p)
    else:
        p = d / CHECKPOINT_FILE
        ck = read_torch_checkpoint(p)
        for what, keys in UNITE_KEYS.items():
            key = next((k for k in keys if k in ck), None)
            if key is None:
                if what in ("bank", "appearance"):
                    continue
                raise ProxycodecError(f"has no {keys[0]!r} state dict (keys: {sorted(map(str, ck))[:8]})", p)
            if what == "appearance":
                table = _embedding_table(ck[key], p)
            else:
                nets[what] = _net_from_state(ck[key], what, p)
    return nets, table


# ---------------------------------------------------------------------------------------------- the model
def _variant(nets: dict[str, _Net], table: np.ndarray | None, F: int, K: int, appearance_row: int,
             cfg: dict, cfg_path: Path | None):
    """Check every network against the anchors and infer the variant -> (DecoderConfig fields, state arrays)."""
    for what, n_out in (("opacity", K), ("cov", 7 * K), ("color", 3 * K)):
        _check_net(nets[what], what, n_out)
    A = 0 if table is None else int(table.shape[1])
    dist = {}
    for what in ("opacity", "cov", "color"):
        extra = nets[what].n_in - F - 3 - (A if what == "color" else 0)
        if extra not in (0, 1):
            app = f" + {A} appearance" if what == "color" and A else ""
            raise ProxycodecError(
                f"the {what} network takes {nets[what].n_in} inputs; Scaffold-GS's take {F} features + 3 view "
                f"direction{app} (+ 1 distance)" + (" (an appearance embedding without embedding_appearance.pt?)"
                                                    if what == "color" and not A and extra > 1 else ""),
                nets[what].source)
        dist[what] = bool(extra)
    hidden = {what: nets[what].hidden for what in ("opacity", "cov", "color")}
    if len(set(hidden.values())) != 1:
        raise ProxycodecError(f"the MLPs' hidden widths differ ({hidden}); this variant cannot be represented "
                              "(one hidden width for all three)", nets["opacity"].source)
    bank = 0
    if "bank" in nets:
        _check_net(nets["bank"], "bank", 3)
        if nets["bank"].n_in != 4:
            raise ProxycodecError(f"the feature bank takes {nets['bank'].n_in} inputs, not 4", nets["bank"].source)
        if F % 4:
            raise ProxycodecError(f"a feature bank needs a feature width divisible by 4, the anchors have {F}",
                                  nets["bank"].source)
        bank = nets["bank"].hidden
    if cfg_path is not None:  # the run's own record must agree with what the files say
        said = {"feat_dim": F, "n_offsets": K, "use_feat_bank": bool(bank), "appearance_dim": A,
                "add_opacity_dist": dist["opacity"], "add_cov_dist": dist["cov"], "add_color_dist": dist["color"]}
        for k, v in said.items():
            if k in cfg and cfg[k] != v:
                raise ProxycodecError(f"cfg_args says {k}={cfg[k]!r} but the PLY and MLP files say {v!r}", cfg_path)
    arrays = {}
    for what, name in (("opacity", "mlp_opacity"), ("cov", "mlp_cov"), ("color", "mlp_color"), ("bank",
                                                                                                "mlp_feature_bank")):
        if what not in nets:
            continue
        (w1, b1), (w2, b2) = nets[what].linears
        if what == "color" and A:
            if not 0 <= appearance_row < table.shape[0]:
                raise ProxycodecError(f"appearance row {appearance_row} does not exist (the embedding has "
                                      f"{table.shape[0]} rows)", nets[what].source)
            n = w1.shape[1] - A
            # [x, e] @ W^T + b = x @ W[:, :n]^T + (b + W[:, n:] e): the fixed row folded into the bias
            b1 = (b1.astype(np.float64) + w1[:, n:].astype(np.float64) @ table[appearance_row].astype(np.float64))
            w1, b1 = np.ascontiguousarray(w1[:, :n]), b1.astype(np.float32)
        arrays.update({f"{name}.0.weight": w1, f"{name}.0.bias": b1, f"{name}.2.weight": w2, f"{name}.2.bias": b2})
    fields = {"hidden": hidden["opacity"], "opacity_dist": dist["opacity"], "cov_dist": dist["cov"],
              "color_dist": dist["color"], "feature_bank": bank}
    return fields, arrays, A


def load_scaffold_output(path: str | os.PathLike, appearance_row: int = 0):
    """A Scaffold-GS output (its folder, an ``iteration_N`` folder or its ``point_cloud.ply`` with the MLP files
    beside it) as a ``SceneModel``: anchors, our decoder holding Scaffold-GS's networks (variant in its
    configuration; FiLM at the identity, gate on), the views of ``cameras.json`` and the background of
    ``cfg_args``. ``appearance_row``: the appearance embedding row used for every view, when there is one."""
    import torch

    from .decoder import DecoderConfig, GaussianDecoder
    from .formats.scaffold_ply import read_scaffold_ply
    from .model import SceneModel
    from .scene import AnchorScene, scene_from_scaffold_ply

    files = find_scaffold_files(path)
    if files is None:
        raise ProxycodecError("not a Scaffold-GS output (no point_cloud/iteration_N/point_cloud.ply, or no "
                              "opacity_mlp.pt / checkpoints.pth beside the PLY)", path)
    ply = read_scaffold_ply(files.ply)
    F, K = ply.feature_dim, ply.n_offsets
    cfg = read_cfg_args(files.cfg_args) if files.cfg_args else {}
    nets, table = _read_networks(files)
    fields, arrays, A = _variant(nets, table, F, K, appearance_row, cfg, files.cfg_args)
    voxel = cfg.get("voxel_size")
    voxel = float(voxel) if isinstance(voxel, (int, float)) and not isinstance(voxel, bool) \
        and math.isfinite(voxel) and voxel > 0 else None  # <= 0: Scaffold-GS chose it from the points; estimate
    scene = scene_from_scaffold_ply(ply, voxel, source=str(files.ply))
    bounds = scene.bounds()
    center = 0.5 * (bounds[0] + bounds[1])
    radius = max(0.5 * float(np.linalg.norm(bounds[1] - bounds[0])), 1e-6)
    dcfg = DecoderConfig(feat_dim=F, n_offsets=K, embedding="film", scene_center=tuple(float(c) for c in center),
                         scene_radius=radius, film_xi_range=(0.1, 1.0), **fields)
    with torch.random.fork_rng():  # the FiLM input layer's init (its output layer is zero): fixed, caller untouched
        torch.manual_seed(0)
        fresh = GaussianDecoder(dcfg)
    decoder = GaussianDecoder.from_arrays(dcfg, {**fresh.state_arrays(), **arrays}).eval()
    cams = read_scaffold_cameras(files.cameras_json) if files.cameras_json else None
    white = cfg.get("white_background", False)
    bg = (1.0, 1.0, 1.0) if white is True else (0.0, 0.0, 0.0)  # Scaffold-GS's default is black
    used = [files.ply, *files.mlp_files()]
    info = {"mode": files.mode, "iteration": files.iteration, "variant": dcfg.variant(),
            "appearance": {"width": A, "rows": int(table.shape[0]), "row": appearance_row} if A else None,
            "files": [p.name for p in used], "bytes": sum(p.stat().st_size for p in used)}
    meta = {"scaffold_gs": info}
    scene = AnchorScene(scene.positions, scene.features, scene.offsets, scene.scalings, scene.voxel_size,
                        {"imported_from": "scaffold-gs", **{k: info[k] for k in ("mode", "iteration", "appearance")}})
    return SceneModel(scene, decoder, cams, bg, meta)
