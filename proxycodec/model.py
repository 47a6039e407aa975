"""An anchor scene together with the decoder that renders it: what ``fit`` writes and ``encode`` reads.

On disk: the anchors as a Scaffold-GS PLY (``scene.ply``) plus our weights sidecar (``scene.weights.pxc``, a
proxycodec container holding the MLP weights as raw float32 arrays and the configuration as JSON). A fresh process
renders it with nothing else. Nothing is ever unpickled.
"""

from __future__ import annotations

import copy
import os
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from .camera import Camera, check_xi
from .decoder import DecoderConfig, GaussianDecoder, NeuralGaussians, visible_anchors
from .errors import ProxycodecError
from .render import GateConfig, RenderResult, project, rasterize
from .scene import AnchorScene

WEIGHTS_KIND = "proxycodec.weights"
WEIGHTS_SUFFIX = ".weights.pxc"


def weights_path_for(ply_path: str | os.PathLike) -> Path:
    p = Path(ply_path)
    return p.with_name(p.stem + WEIGHTS_SUFFIX)


@dataclass
class SceneRender(RenderResult):
    gaussians: NeuralGaussians | None = None
    visible_anchor_index: torch.Tensor | None = None


def scene_visible(scene: AnchorScene, decoder: GaussianDecoder, camera: Camera) -> torch.Tensor:
    """Indices of the anchors of ``scene`` whose Gaussians can reach ``camera``'s frustum (at its render size)."""
    return visible_anchors(scene.positions.detach(), scene.extent_radius().detach(), camera,
                           decoder.config.near_plane())


def decode_view(scene: AnchorScene, decoder: GaussianDecoder, camera: Camera, xi: float,
                features: torch.Tensor | None = None, offsets: torch.Tensor | None = None,
                visible: torch.Tensor | None = None) -> tuple[NeuralGaussians, torch.Tensor]:
    """Neural Gaussians of the anchors visible from ``camera`` (already at its render resolution).

    ``features`` (``offsets``) override the scene's (stage 2 renders leaves with predicted ones). ``visible``:
    ``scene_visible(scene, decoder, camera)`` where the caller has it already. Returns the Gaussians
    (``anchor_index`` into the full scene) and the visible anchor indices.
    """
    vis = scene_visible(scene, decoder, camera) if visible is None else visible
    feats = scene.features if features is None else features
    offs = scene.offsets if offsets is None else offsets
    _, _, center = camera.torch_params(scene.positions.device, scene.positions.dtype)
    g = decoder(scene.positions[vis], feats[vis], offs[vis], scene.scalings[vis], center, xi)
    g.anchor_index = vis[g.anchor_index]
    return g, vis


def render_scene(
    scene: AnchorScene,
    decoder: GaussianDecoder,
    camera: Camera,
    xi: float = 1.0,
    *,
    background=(1.0, 1.0, 1.0),
    backend: str = "auto",
    features: torch.Tensor | None = None,
    offsets: torch.Tensor | None = None,
    gate: GateConfig | None = None,
    size: tuple[int, int] | None = None,
    visible: torch.Tensor | None = None,
) -> SceneRender:
    """Render ``scene`` from ``camera`` (given at its 100% reference size) at resolution ratio ``xi``: at
    ``camera.scaled(xi)``'s size, or at ``size`` (width, height) where given (the embedding still sees ``xi``).
    ``visible``: the anchors ``scene_visible`` gives for that camera, where the caller has them already."""
    xi = check_xi(xi)
    cam = camera.scaled(xi) if size is None else camera.sized(*size)
    g, vis = decode_view(scene, decoder, cam, xi, features, offsets, visible)
    bg = torch.as_tensor(background, dtype=scene.positions.dtype, device=scene.positions.device)
    proj = project(g.means, g.quats, g.scales, g.opacities, g.colors, cam,
                   gate=decoder.config.gate if gate is None else gate, near=decoder.config.near_plane(), origin=g.origin,
                   backend=backend)
    image, alpha = rasterize(proj, bg, backend)
    return SceneRender(image=image, alpha=alpha, projected=proj, gaussians=g, visible_anchor_index=vis)


@dataclass
class SceneModel:
    """Anchors + decoder (+ the cameras the scene was made with, when known)."""

    scene: AnchorScene
    decoder: GaussianDecoder
    cameras: list[Camera] | None = None
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    meta: dict = field(default_factory=dict)  # the weights sidecar's metadata when loaded from files

    @property
    def device(self) -> torch.device:
        return self.scene.positions.device

    def to(self, device) -> SceneModel:
        """This model on ``device`` (a copy: this one stays where it is; itself when already there)."""
        if torch.device(device) == self.device:
            return self
        return replace(self, scene=self.scene.to(device), decoder=copy.deepcopy(self.decoder).to(device))

    def render(self, camera: Camera, xi: float = 1.0, *, backend: str = "auto",
               size: tuple[int, int] | None = None) -> SceneRender:
        with torch.no_grad():
            return render_scene(self.scene, self.decoder, camera, xi, background=self.background, backend=backend,
                                size=size)

    # ------------------------------------------------------------------ persistence
    def save(self, ply_path: str | os.PathLike, extra_meta: dict | None = None,
             extra_arrays: dict[str, np.ndarray] | None = None) -> tuple[Path, Path]:
        """Write the anchor PLY and its weights sidecar as a pair.

        Both are written to temporary files first and renamed only when both are complete (weights first), so an
        interrupt never leaves a PLY without weights. The sidecar records the PLY's size and CRC32; ``load`` refuses
        a pair that does not belong together (e.g. a PLY replaced by another tool).
        """
        from .formats.container import write_container
        from .formats.scaffold_ply import ScaffoldPly, write_scaffold_ply

        s = self.scene
        ply_path = Path(ply_path)
        wpath = weights_path_for(ply_path)
        tmp_ply = ply_path.with_name(f".{ply_path.name}.{os.getpid()}.pair.tmp")
        tmp_w = wpath.with_name(f".{wpath.name}.{os.getpid()}.pair.tmp")
        try:
            write_scaffold_ply(tmp_ply, ScaffoldPly(
                positions=s.positions.detach().cpu().numpy(), offsets=s.offsets.detach().cpu().numpy(),
                features=s.features.detach().cpu().numpy(), scalings=s.scalings.detach().cpu().numpy()))
            ply_bytes = tmp_ply.read_bytes()
            meta = {
                "kind": WEIGHTS_KIND,
                "decoder": self.decoder.config.to_json(),
                "voxel_size": s.voxel_size,
                "background": list(self.background),
                "cameras": [c.to_json() for c in self.cameras] if self.cameras else [],
                "scene": {k: v for k, v in s.metadata.items()},
                "anchor_ply": {"bytes": len(ply_bytes), "crc32": zlib.crc32(ply_bytes)},
                **(extra_meta or {}),
            }
            arrays = self.decoder.state_arrays()
            for k, v in (extra_arrays or {}).items():
                if k in arrays:
                    raise ProxycodecError(f"weights section {k!r} collides with a decoder weight")
                arrays[k] = v
            write_container(tmp_w, meta, arrays)
            os.replace(tmp_w, wpath)
            os.replace(tmp_ply, ply_path)
        except BaseException:
            for t in (tmp_ply, tmp_w):
                t.unlink(missing_ok=True)
            raise
        return ply_path, wpath

    @staticmethod
    def load(ply_path: str | os.PathLike, weights_path: str | os.PathLike | None = None) -> SceneModel:
        from .formats.container import read_container
        from .formats.scaffold_ply import read_scaffold_ply
        from .scene import scene_from_scaffold_ply

        ply_path = Path(ply_path)
        ply = read_scaffold_ply(ply_path)  # the anchors' own problems first
        wpath = Path(weights_path) if weights_path else weights_path_for(ply_path)
        if not wpath.exists():
            raise ProxycodecError(f"no decoder weights beside the anchor PLY (expected {wpath.name}, or "
                                  "Scaffold-GS's opacity_mlp.pt/cov_mlp.pt/color_mlp.pt or checkpoints.pth)",
                                  ply_path)
        c = read_container(wpath)
        if c.meta.get("kind") != WEIGHTS_KIND:
            raise ProxycodecError(f"not a weights file (kind {c.meta.get('kind')!r})", wpath)
        pair = c.meta.get("anchor_ply")
        if isinstance(pair, dict) and "crc32" in pair:
            data = ply_path.read_bytes()
            if len(data) != pair.get("bytes") or zlib.crc32(data) != pair.get("crc32"):
                raise ProxycodecError(f"weights file {wpath.name} was written for a different anchor PLY "
                                      "(size/CRC32 mismatch)", ply_path)
        try:
            cfg = DecoderConfig.from_json(c.meta["decoder"])
            decoder = GaussianDecoder.from_arrays(cfg, c.arrays)
            cams = [Camera.from_json(d) for d in c.meta.get("cameras", [])]
            bg = tuple(float(x) for x in c.meta.get("background", (1, 1, 1)))
            voxel = float(c.meta["voxel_size"])
        except (KeyError, TypeError, ValueError) as e:
            raise ProxycodecError(f"bad weights file: {e}", wpath) from None
        scene = scene_from_scaffold_ply(ply, voxel, source=str(ply_path))
        if scene.feat_dim != cfg.feat_dim or scene.n_offsets != cfg.n_offsets:
            raise ProxycodecError(f"anchors have {scene.feat_dim} features x {scene.n_offsets} offsets but the "
                                  f"decoder expects {cfg.feat_dim} x {cfg.n_offsets}", ply_path)
        scene = AnchorScene(scene.positions, scene.features, scene.offsets, scene.scalings, voxel,
                            dict(c.meta.get("scene", {})))
        decoder.eval()
        return SceneModel(scene, decoder, cams or None, bg, dict(c.meta))  # type: ignore[arg-type]


def image_to_uint8(image: torch.Tensor) -> np.ndarray:
    return (image.detach().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)


def reference_width(model) -> int | None:
    """The 100% reference width ``model`` was trained at: its cameras' widest (a fitted scene and a container carry
    the fit's cameras at that width); None for a model without cameras (a plain 3DGS PLY)."""
    widths = [int(c.width) for c in getattr(model, "cameras", None) or []]
    return max(widths) if widths else None


ANTIALIASED_MODES = ("scene", "on", "off")


def apply_antialiased_mode(model, mode: str) -> bool:
    """Force the antialiased filter's opacity compensation (``GateConfig.antialiased``) on or off for rendering
    (``mode`` "on" / "off"), or leave the scene's own setting ("scene": an anchor scene's decoder; a plain 3DGS
    file's flag, which an SPZ or GLB carries and an INRIA PLY does not: a gsplat PLY trained ``antialiased`` needs
    "on"). Works on anchor scenes and plain 3DGS models alike. Returns the setting now in effect."""
    forced = antialiased_override(mode)
    dec = getattr(model, "decoder", None)
    if dec is None:  # a plain 3DGS model (explicit.ExplicitModel)
        if forced is not None:
            model.antialiased = forced
        return bool(model.antialiased)
    if forced is not None:
        cfg = dec.config
        dec.config = replace(cfg, gate=replace(cfg.gate, antialiased=forced))
    return bool(dec.config.gate.antialiased)


def antialiased_override(mode: str) -> bool | None:
    """``--antialiased`` / ``--source-antialiased``'s ``mode`` -> None ("scene": the scene's own setting), True
    ("on") or False ("off")."""
    if mode not in ANTIALIASED_MODES:
        raise ProxycodecError(f"antialiased mode must be scene, on or off, got {mode!r}")
    return None if mode == "scene" else mode == "on"


def apply_gate_mode(model, mode: str) -> dict | None:
    """Force the coverage gate of an anchor model on or off for rendering (``mode`` "on" / "off"), or leave the
    model's own setting ("model"). Returns the gate configuration now in effect (None for a plain 3DGS model, which
    has no gate). "on" uses the kappa / eta stored with the decoder, so a model trained with ``--no-gate`` is gated
    post hoc with the values it would have been trained with."""
    if mode not in ("model", "on", "off"):
        raise ProxycodecError(f"gate mode must be model, on or off, got {mode!r}")
    dec = getattr(model, "decoder", None)
    if dec is None:
        if mode != "model":
            raise ProxycodecError("--gate applies to anchor scenes; a plain 3DGS PLY is rendered without a gate")
        return None
    if mode != "model":
        cfg = dec.config
        dec.config = replace(cfg, gate=replace(cfg.gate, enabled=(mode == "on")))
    return dec.config.gate.to_json()
