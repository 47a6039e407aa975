"""``encode``, ``decode`` and ``stats``: the codec's commands (a thin layer over ``proxycodec.codec``)."""

from __future__ import annotations

import functools
import json
import time
from pathlib import Path

import click

from ..errors import ProxycodecError
from ..sections import WEIGHT_DTYPES
from .common import (
    command_device, config_option, on_device, parse_resolutions, render_views, supersample_option, user_errors,
)
from .convert import convert_options

#: An option whose default is ``EncodeConfig``'s field of the same name.
encode_option = functools.partial(config_option, "proxycodec.codec:EncodeConfig")


def _stderr(msg: str) -> None:
    click.echo(msg, err=True)


@click.command()
@click.argument("scene", type=click.Path())
@click.option("-o", "--out", "out", type=click.Path(dir_okay=False), default=None,
              help="Output container (default: SCENE with suffix .pxc; a folder: its name + .pxc beside it).")
@click.option("--weights", type=click.Path(dir_okay=False), default=None,
              help="Decoder weights (default: SCENE.weights.pxc beside the PLY).")
@encode_option("--proxy-ratio", show_default=True, type=float, help="rho: share of proxies per cell.")
@encode_option("--proxy-selection", type=click.Choice(["random", "spread"]), show_default=True,
               help="Proxies per cell at random (the paper's) or spread out (greedy k-median), when not as fitted.")
@encode_option("--cell-size", type=float,
               help="Proxy-selection cell size in world units (default: a voxel multiple giving ~10 anchors/cell).")
@encode_option("--feature-bits", show_default=True, type=int, help="Proxy features (1-16, 32 = float).")
@encode_option("--offset-bits", show_default=True, type=int, help="Offsets (1-16, 32 = float).")
@encode_option("--scaling-bits", show_default=True, type=int, help="Scalings (1-16, 32 = float).")
@encode_option("--weights-dtype", show_default=True, type=click.Choice(list(WEIGHT_DTYPES)),
               help="MLP weights precision (qN: int8 matrices on a grid of 2^(N-1)-1 levels each side, per-row "
                    "scales; every qN reads as q8 does).")
@encode_option("--max-cameras", show_default=True, type=int,
               help="Default cameras kept in the container (evenly spaced).")
@encode_option("--predict-offsets/--store-offsets",
               help="Predict leaf offsets too instead of storing them [default: as the scene's stage-2 predictor "
                    "(fit --predict-offsets), else store].")
@encode_option("--drop-dead-offsets/--keep-dead-offsets", show_default=True,
               help="Store the offsets of neural Gaussians that are never drawn as 0 (-1.5% bytes, ~9x encode time).")
@encode_option("--predictor-context", show_default=True, type=click.IntRange(1, 8),
               help="Proxies the predictor sees per leaf (the nearest, plus context), when not as fitted.")
@encode_option("--predictor-iters", show_default=True, type=int)
@encode_option("--leaf-sample", show_default=True, type=float,
               help="Fraction of the leaves in each predictor iteration (L_recon).")
@encode_option("--zstd-level", show_default=True, type=int)
@encode_option("--entropy", show_default=True, type=click.Choice(["auto", "model", "zstd"]),
               help="model: arithmetic-code proxy features, scalings and offsets under the conditional entropy model "
                    "fitted to the scene (scene format 4); zstd: zstd alone (scene format 2); auto: the model where "
                    "it is smaller.")
@encode_option("--entropy-iters", show_default=True, type=int, help="Iterations fitting the entropy model.")
@encode_option("--positions", show_default=True, type=click.Choice(["octree", "delta"]),
               help="Grid positions: an octree of them, binary arithmetic-coded (scene format 6: a third to a half "
                    "fewer position bytes), or per-axis deltas in Morton order (zstd; scene formats 2-5, for "
                    "readers older than format 6).")
@encode_option("--lambda-rate", show_default=True, type=click.FloatRange(0.0),
               help="With distillation: weight of the rate term (noise quantisation, learned steps per channel).")
@encode_option("--quant-cells", show_default=True, type=click.IntRange(0, 32),
               help="With distillation and --lambda-rate: learn per-cell quantisation levels (as fit --quant-cells).")
@encode_option("--learned-steps/--no-learned-steps", show_default=True,
               help="Quantise with the steps rate training learned (fit --lambda-rate) instead of the bit depths.")
@encode_option("--seed", show_default=True, type=int)
@click.option("--refit-predictor", is_flag=True,
              help="Ignore a stage-2 predictor/proxy split stored by `fit`; select proxies and fit anew.")
@encode_option("--distill/--no-distill",
               help="Force the path for a scene without a stage-2 predictor: fine-tune the proxy scene against the "
                    "source's own renders (no images needed), or fit the predictor on feature distance (L_recon) "
                    "alone [default: decided by measurement: L_recon first, distilled only when its decoded scene "
                    "falls below --distill-threshold against the source].")
@encode_option("--distill-threshold", show_default=True, type=float,
               help="dB: the default path distils when the L_recon encode decodes below this, against the source "
                    "rendered at the same resolution (held-out views at 10%, 30%, 100%).")
@encode_option("--distill-iters", show_default=True, type=int, help="Distillation iterations.")
@encode_option("--distill-time-budget", type=float,
               help="Seconds of distillation (with --distill-iters, whichever ends first).")
@encode_option("--distill-views", show_default=True, type=int,
               help="Teacher views at least (automatic views around the scene are added up to this many).")
@encode_option("--distill-full-share", show_default=True, type=click.FloatRange(0.0, 1.0),
               help="Share of distillation iterations at 100% (as fit --xi-full-share; anchor scenes: a 3DGS "
                    "PLY's conversion keeps its own, 0).")
@encode_option("--distill-targets", show_default=True, type=click.Choice(["auto", "whole", "full"]),
               help="The teacher's target at a training resolution: its render at the largest whole multiple of the "
                    "size within 100%, box-filtered by it (whole), or its 100% render box-filtered down (full); "
                    "auto: whole for a scene fitted at random resolutions, else full.")
@encode_option("--images", type=click.Path(exists=True, file_okay=False),
               help="Distil against this dataset's photos (Blender or COLMAP folder) instead of the source's renders.")
@click.option("--keep-anchor-scene", type=click.Path(dir_okay=False), default=None,
              help="An INRIA 3DGS PLY: keep the converted anchor scene (PLY + weights) here.")
@convert_options
@click.option("--json", "as_json", is_flag=True, help="Print the encode report as JSON on stdout.")
@user_errors
def encode(scene, out, weights, proxy_ratio, proxy_selection, cell_size, feature_bits, offset_bits, scaling_bits,
           weights_dtype, predict_offsets, max_cameras, drop_dead_offsets, predictor_context, predictor_iters, leaf_sample,
           zstd_level,
           entropy, entropy_iters, positions, lambda_rate, quant_cells, learned_steps, seed,
           refit_predictor, distill, distill_threshold, distill_iters, distill_time_budget, distill_views,
           distill_full_share,
           distill_targets, images, keep_anchor_scene,
           voxel_size, max_anchors, target_size, views, view_size, background, max_width, source_antialiased,
           as_json) -> None:
    """Compress SCENE to a proxy-anchor container (writes OUT, default SCENE.pxc; prints its size).

    SCENE: an anchor scene (PLY + its .weights.pxc sidecar, e.g. from `proxycodec fit` or `sample`), a trained
    Scaffold-GS output (its folder, or its point_cloud.ply with the MLP files beside it), or an INRIA 3DGS PLY.

    \b
    What happens by default:
    - a scene with a stage-2 predictor (`fit` without --no-proxies): its proxies and predictor are used as fitted;
      seconds.
    - a scene without one (fit --no-proxies, a Scaffold-GS output, the sample): the predictor is fitted on feature
      distance (L_recon, seconds), the decoded scene is rendered against the source on held-out views at 10%, 30%
      and 100%, and one line says which path is taken: that encode is kept at or above --distill-threshold dB,
      else the scene is distilled (fine-tuned against the source's own renders at random resolutions, no images
      needed; minutes: lego ~15 on 2 cores) and the report gives its held-out PSNR against the source.
    - an INRIA 3DGS PLY: converted first (`proxycodec convert`: anchors from its Gaussians, trained against its own
      renders on its --background), then its anchor scene (with its stage-2 predictor) is encoded.
    """
    from .. import codec
    from ..formats.splats import splat_kind

    p = Path(scene)
    out = out or str(p.resolve().with_name(p.resolve().name + ".pxc") if p.is_dir() else p.with_suffix(".pxc"))
    knobs = dict(proxy_ratio=proxy_ratio, proxy_selection=proxy_selection, cell_size=cell_size,
                 feature_bits=feature_bits, offset_bits=offset_bits, scaling_bits=scaling_bits,
                 weights_dtype=weights_dtype, predict_offsets=predict_offsets, max_cameras=max_cameras,
                 predictor_context=predictor_context, predictor_iters=predictor_iters, leaf_sample=leaf_sample, zstd_level=zstd_level, seed=seed,
                 entropy=entropy, entropy_iters=entropy_iters, positions=positions, lambda_rate=lambda_rate,
                 quant_cells=quant_cells, learned_steps=learned_steps)
    if not p.is_dir() and splat_kind(p):
        from ..convert import convert_and_encode
        from .convert import make_config

        if images or weights or distill is not None or distill_targets != "auto":
            raise ProxycodecError("--images, --weights, --distill/--no-distill and --distill-targets do not apply to a "
                                  "3DGS PLY (it is converted against its own 100% renders, box-filtered down)", p)
        # conversion's own length (ConvertConfig: 4000 iterations) unless --distill-iters is given: encode's default
        # is the distillation's, measured for anchor scenes
        given = click.get_current_context().get_parameter_source("distill_iters") != click.core.ParameterSource.DEFAULT
        cfg = make_config(distill_iters if given else None, distill_time_budget, seed, voxel_size, views, view_size,
                          background, max_width, max_anchors, target_size, source_antialiased=source_antialiased)
        _, r = convert_and_encode(p, out, cfg, keep=keep_anchor_scene, log=_stderr, device=command_device(), **knobs)
    else:
        if background is not None:
            raise ProxycodecError("--background applies to a 3DGS PLY; an anchor scene keeps the background it was "
                                  "trained on", p)
        if source_antialiased != "scene":
            raise ProxycodecError("--source-antialiased applies to a 3DGS PLY, SPZ or GLB (how its Gaussians render); "
                                  "an anchor scene keeps its own setting", p)
        if max_anchors is not None or target_size is not None:
            raise ProxycodecError("--max-anchors and --target-size apply to a 3DGS PLY (they choose its anchors); "
                                  "an anchor scene keeps its own", p)
        source = (scene, weights) if weights else scene
        r = codec.encode(source, out, **knobs, use_fitted=not refit_predictor, drop_dead_offsets=drop_dead_offsets,
                         distill=distill, distill_threshold=distill_threshold, distill_iters=distill_iters,
                         distill_time_budget=distill_time_budget,
                         distill_views=distill_views, distill_full_share=distill_full_share,
                         distill_targets=distill_targets, images=images,
                         progress=_stderr, device=command_device())
    if as_json:
        click.echo(json.dumps(r.to_json(), indent=2))
    else:
        what = "the 3DGS PLY" if r.meta.get("convert") else "PLY + weights"
        ratio = f", {r.ratio:.1f}x smaller than {what}" if r.ratio else ""
        click.echo(f"wrote {r.path}: {r.file_bytes:,} B for {r.anchors} anchors ({r.proxies} proxies){ratio} "
                   f"in {r.seconds['total']:.1f} s; {choice_text(r.meta.get('encode_choice'))}")


def choice_text(choice) -> str:
    """The path encode took, in words (the encode summary and ``stats``)."""
    if not isinstance(choice, dict):
        return "path not recorded"
    path = choice.get("path")
    if choice.get("measured") is not None:
        return (f"path {path} chosen by measurement: the L_recon encode decoded at {choice['measured']:.2f} dB "
                f"against the source, threshold {choice.get('threshold')} dB")
    return f"path {path}" + (" (forced)" if choice.get("forced") else "")


def load_cameras(spec: str):
    """Cameras from a cameras.json (a list of camera records, or {"cameras": [...]}) or a dataset folder."""
    from ..camera import Camera

    p = Path(spec)
    if p.is_dir():
        from ..formats.datasets import load_dataset

        return list(load_dataset(p).cameras)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise ProxycodecError("no such cameras file or dataset folder", p) from None
    except (UnicodeDecodeError, ValueError) as e:
        raise ProxycodecError(f"cameras file is not valid JSON ({e})", p) from None
    if isinstance(data, dict):
        data = data.get("cameras")
    if not isinstance(data, list) or not data:
        raise ProxycodecError("cameras file must hold a non-empty list of cameras", p)
    try:
        return [Camera.from_json(d) for d in data]
    except ProxycodecError as e:
        raise ProxycodecError(e.reason, p) from None
    except AttributeError:
        raise ProxycodecError("each camera must be a JSON object", p) from None


@click.command()
@click.argument("container", type=click.Path(dir_okay=False))
@click.option("--res", "res", default="1.0", show_default=True,
              help="Comma-separated resolution ratios in [0.025, 2.0] (an export takes one).")
@click.option("--cameras", "cameras", type=click.Path(), default=None,
              help="A dataset folder or cameras.json (default: the stored cameras, else an orbit).")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Folder for the PNGs (default: CONTAINER without suffix + _renders).")
@click.option("--view", "views", multiple=True, type=int, help="Camera index (repeatable; default: all).")
@click.option("--no-render", is_flag=True, help="Only decode (and export); render nothing.")
@click.option("--ply", "ply", type=click.Path(dir_okay=False), default=None,
              help="Export the Gaussians decoded for --res as a standard INRIA 3DGS PLY.")
@click.option("--spz", "spz", type=click.Path(dir_okay=False), default=None,
              help="Export them as SPZ (version 4).")
@click.option("--glb", "glb", type=click.Path(dir_okay=False), default=None,
              help="Export them as glTF 2.0 binary with KHR_gaussian_splatting.")
@click.option("--lod", "lod", type=click.Path(file_okay=False), default=None,
              help="Write a level-of-detail set to this folder: one file per --levels entry plus lod.json.")
@click.option("--levels", default=",".join(f"{x:g}" for x in (1.0, 0.5, 0.25, 0.125)), show_default=True,
              help="Resolution ratios of the LOD levels, finest first.")
@click.option("--lod-format", default="spz", show_default=True, type=click.Choice(["spz", "ply", "glb"]),
              help="File format of the LOD levels.")
@click.option("--sh-degree", default=1, show_default=True, type=click.IntRange(0, 3),
              help="Exported colour: SH of this degree fitted to the decoded colours over the bake's views.")
@click.option("--bake-view", default=None, type=int,
              help="Export the colours of this stored camera instead (SH degree 0).")
@click.option("--backend", default="auto", show_default=True,
              type=click.Choice(["auto", "reference", "cpu", "cuda"]), help="Compositing backend.")
@supersample_option
@user_errors
def decode(container, res, cameras, out_dir, views, no_render, ply, spz, glb, lod, levels, lod_format, sh_degree,
           bake_view, backend, supersample) -> None:
    """Decode CONTAINER (the leaves' features regenerated from their nearest proxies by its residual predictor)
    and render its views at any resolution: PNGs in OUT (default CONTAINER_renders/viewNNN_resX.XXX.png), on the
    background the scene was trained on.

    --ply, --spz and --glb export the Gaussians decoded for one resolution (--res) as a plain 3DGS set: opacities
    gated for that resolution (what the gate switches off is left out), colours as SH fitted over many views.
    --lod writes one such file per level. With an export, PNGs are rendered only when -o or --view asks for them.

    Rendering on the CPU without an export never imports torch (numpy + the numba kernels, the same results);
    exports, --backend reference|cuda, --supersample above 1 and containers that path does not cover take the torch
    path."""
    from ..scenes import decode_torch_free

    resolutions = parse_resolutions(res)
    exports = {k: v for k, v in (("ply", ply), ("spz", spz), ("glb", glb)) if v}
    exporting = bool(exports or lod)
    if exports and len(resolutions) != 1:
        raise ProxycodecError(f"--ply/--spz/--glb export one resolution; --res gives {len(resolutions)}")
    lod_levels = None
    if lod:
        from ..export import parse_levels  # torch: only where an export asks

        lod_levels = parse_levels(levels)
    if lod and bake_view is not None:
        raise ProxycodecError("--bake-view applies to --ply/--spz/--glb, not to --lod")
    t0 = time.perf_counter()
    # the torch-free path (CPU) unless torch is asked for: an export, a torch backend, or --device cuda
    lite = decode_torch_free(container) if backend in ("auto", "cpu") and not exporting and supersample == 1 \
        and not _cuda_asked() else None
    if lite is not None:
        from ..lite import default_cameras

        model, n_anchors = lite, lite.num_anchors
    else:
        from .. import codec

        model = on_device(codec.decode(container))
        default_cameras, n_anchors = codec.default_cameras, model.scene.num_anchors
    _stderr(f"decoded {n_anchors} anchors in {time.perf_counter() - t0:.2f} s")
    cams = load_cameras(cameras) if cameras else default_cameras(model)
    model.cameras = cams
    if exporting:
        _export(model, container, exports, resolutions[0], lod, lod_levels, lod_format, sh_degree, bake_view)
    if not no_render and (not exporting or out_dir or views):
        out = Path(out_dir) if out_dir else Path(container).with_suffix("").with_name(
            Path(container).stem + "_renders")
        render_views(model, resolutions, out, list(views) or None, backend, supersample=supersample)


def _cuda_asked() -> bool:
    """Whether ``--device cuda`` was given (``auto`` does not import torch here: decode stays torch-free)."""
    from ..devices import CUDA, name_from_env

    return name_from_env() == CUDA


def _export(model, container, exports: dict, xi: float, lod, levels, lod_format: str, sh_degree: int,
            bake_view) -> None:
    from ..export import LOD_MANIFEST, BakeConfig, bake, write_gaussians, write_lod

    if exports:
        t = time.perf_counter()
        baked = bake(model, BakeConfig(xi=xi, sh_degree=sh_degree, view=bake_view))
        i = baked.info
        _stderr(f"decoded for resolution {xi:g} from {i['views']} views in {time.perf_counter() - t:.1f} s: "
                f"{i['gaussians']} of {i['slots']} neural Gaussians kept ({i['below_min_opacity']} gated or "
                f"faded below 1/255, {i['never_shown']} never shown); colour {i['colour']}")
        for fmt, path in exports.items():
            n = write_gaussians(path, baked.ply, fmt)
            click.echo(f"wrote {path}: {baked.ply.n_gaussians} Gaussians, {n} B ({fmt}, resolution {xi:g}, "
                       f"colour {i['colour']})")
    if lod:
        m = write_lod(model, lod, levels, fmt=lod_format, sh_degree=sh_degree, source=Path(container).name,
                      log=_stderr)
        click.echo(f"wrote {Path(lod) / LOD_MANIFEST}: {m['lodLevels']} levels, "
                   + ", ".join(f"{e['resolution']:g}: {e['count']} Gaussians {e['bytes']} B" for e in m["levels"]))


@click.command()
@click.argument("file", type=click.Path())
@click.option("--json", "as_json", is_flag=True, help="Everything as JSON (metadata included).")
@user_errors
def stats(file, as_json) -> None:
    """What FILE holds and what each part costs in bytes (the parts add up to the file); writes nothing.

    FILE: a container (anchors, proxies and leaves, quantisation, the path encode took and its measurement, the
    distillation's held-out report, every section), an anchor PLY (+ weights), a Scaffold-GS output or an INRIA
    3DGS PLY."""
    from .. import codec
    from ..distill import report_line

    s = codec.stats(file)
    if as_json:
        click.echo(json.dumps(s, indent=2))
        return
    if s["type"] == "inria-3dgs-ply":
        click.echo(f"{s['file']}: INRIA 3DGS PLY, {s['gaussians']:,} Gaussians, SH degree {s['sh_degree']}, "
                   f"{s['file_bytes']:,} B" + (f" ({s['bytes_per_gaussian']:.0f} B per Gaussian)"
                                               if s["gaussians"] else ""))
        click.echo(f"  {'header':10s} {s['header_bytes']:12,} B")
        for k, v in s["bytes_by_group"].items():
            if v:
                click.echo(f"  {k:10s} {v:12,} B")
        if s["trailing_bytes"]:
            click.echo(f"  {'trailing':10s} {s['trailing_bytes']:12,} B")
        click.echo(f"  `proxycodec convert {s['file']} -o scene.ply` makes an anchor scene of it; "
                   f"`proxycodec encode {s['file']}` converts and compresses it")
        return
    if s["type"] in ("spz", "glb"):
        extra = ", ".join(f"{k} {v}" for k, v in s["header"].items())
        click.echo(f"{s['file']}: {s['what']}, {s['gaussians']:,} Gaussians, SH degree {s['sh_degree']}, "
                   f"{s['file_bytes']:,} B ({s['bytes_per_gaussian']:.1f} B per Gaussian); {extra}")
        click.echo(f"  `proxycodec render {s['file']}` renders it as plain 3DGS; `proxycodec encode {s['file']}` "
                   "converts and compresses it")
        return
    if s["type"] == "ply":
        sg = s.get("scaffold_gs")
        what = f"Scaffold-GS output ({sg['mode']} MLP files: {', '.join(sg['mlp_files'])})" if sg else \
            "Scaffold-GS anchor PLY"
        click.echo(f"{s['file']}: {what}, {s['anchors']} anchors")
        click.echo(f"  PLY {s['file_bytes']:,} B + {'MLPs' if sg else 'weights'} {s['weights_bytes'] or 0:,} B = "
                   f"{s['total_bytes']:,} B ({s['bits_per_anchor']:.0f} bits/anchor)" if s["anchors"] else "  empty")
        click.echo(f"  {'header':10s} {s['header_bytes']:12,} B")
        for k, v in s["raw_bytes_by_group"].items():
            if v or k != "other":
                click.echo(f"  {k:10s} {v:12,} B")
        if s["trailing_bytes"]:
            click.echo(f"  {'trailing':10s} {s['trailing_bytes']:12,} B")
        return
    fmt = ""
    if s.get("scene_format") is not None:
        meta = s.get("metadata")
        feats = meta.get("features") if isinstance(meta, dict) else None
        fmt = f" (scene format {s['scene_format']}" + (f": {', '.join(map(str, feats))}" if isinstance(feats, list)
                                                        else "") + ")"
    click.echo(f"{s['file']}: proxycodec container v{s['format_version']}, kind {s['kind']}{fmt}, "
               f"{s['file_bytes']:,} B")
    if s.get("anchors") is not None and s["kind"] == "proxycodec.scene":
        kind = (s["metadata"].get("source") or {}).get("kind") if isinstance(s["metadata"], dict) else None
        what = "the 3DGS PLY" if kind == "inria-3dgs" else "PLY + weights"
        ratio = f", {s['ratio']:.1f}x smaller than {what} ({s['source_bytes']:,} B)" if s["ratio"] else ""
        click.echo(f"  {s['anchors']} anchors = {s['proxies']} proxies + {s['leaves']} leaves; "
                   f"{s['bits_per_anchor']:.1f} bits/anchor{ratio}")
        p = s.get("proxy") or {}
        click.echo(f"  positions {s['positions']}, offsets {s['offsets']}, bits {s['quant_bits']}, "
                   f"weights {s['weights_dtype']}, cell {p.get('cell_size_voxels', 0):g} voxels, seed {p.get('seed')}")
        for k, lv in (s.get("quant_levels") or {}).items():
            click.echo(f"  {k}: per-cell quantisation levels (step x 2^(level/4)) on a {lv['cells']}^3 grid, "
                       f"{lv['entries']} occupied cells (section quant/levels)")
        cv = s["metadata"].get("convert") if isinstance(s["metadata"], dict) else None
        if isinstance(cv, dict) and isinstance(cv.get("report"), dict):
            click.echo(f"  converted from the 3DGS PLY {(cv.get('source') or {}).get('name')}: "
                       f"{cv.get('iterations')} iterations against its renders; held-out PSNR vs them: "
                       + report_line(cv["report"].get("converted") or {}))
        click.echo(f"  encode {choice_text((s['metadata'] or {}).get('encode_choice'))}")
        d = s.get("distill") or {}
        rep = d.get("held_out") if isinstance(d, dict) else None
        if isinstance(rep, dict) and isinstance(rep.get("per_resolution"), list):
            src = f"the photos of {d['images']}" if d.get("images") else "the source's renders" + (
                f" ({d['targets']} targets)" if d.get("targets") else "")
            click.echo(f"  distilled {d.get('iterations')} iterations against {src}; decoded vs source renders on "
                       f"{len(rep.get('views', []))} held-out views: " + report_line(rep))
    click.echo(f"  {'section':34s} {'dtype':>6s} {'shape':>14s} {'stored':>10s} {'raw':>10s}")
    click.echo(f"  {'(header + table of contents)':34s} {'':>6s} {'':>14s} {s['header_and_toc_bytes']:10,}")
    for sec in s["sections"]:
        shape = "x".join(map(str, sec["shape"]))
        click.echo(f"  {sec['name']:34s} {sec['dtype']:>6s} {shape:>14s} {sec['stored_bytes']:10,} "
                   f"{sec['raw_bytes']:10,}")
