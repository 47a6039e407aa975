"""``sample``, ``render`` and ``demo``: the built-in scene, rendering an anchor scene, the whole pipeline."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from ..fileio import atomic_write
from .common import (
    antialiased_option, background_option, command_device, on_device, parse_resolutions, render_views,
    supersample_option, user_errors,
)


@click.command()
@click.argument("out", type=click.Path(dir_okay=False), default="sample.ply")
@click.option("--seed", default=0, show_default=True, help="Seed of the procedural scene.")
@user_errors
def sample(out: str, seed: int) -> None:
    """Write the built-in procedural scene (6,571 anchors, no training needed) as an anchor PLY OUT and its MLPs
    as OUT.weights.pxc. It has no stage-2 predictor: `proxycodec encode OUT` fits one on L_recon (seconds),
    measures it and keeps it."""
    from ..sample import sample_model

    model = sample_model(seed)
    ply, weights = model.save(out)
    click.echo(f"wrote {ply} ({model.scene.num_anchors} anchors) and {weights}")


@click.command()
@click.argument("scene", type=click.Path())
@click.option("--res", "res", default="1.0,0.5,0.25,0.1", show_default=True,
              help="Comma-separated resolution ratios in [0.025, 2.0].")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False), default="renders", show_default=True)
@click.option("--view", "views", multiple=True, type=int, help="Camera index (repeatable; default: all stored).")
@click.option("--backend", default="auto", show_default=True,
              type=click.Choice(["auto", "reference", "cpu", "cuda"]), help="Compositing backend.")
@supersample_option
@background_option("the scene's own (an anchor scene or container: the one it was trained on; a 3DGS PLY: "
                   "white_background in the trainer's cfg_args beside it or two folders up, else black)")
@antialiased_option("the scene")
@user_errors
def render(scene: str, res: str, out_dir: str, views: tuple[int, ...], backend: str, supersample: int,
           background, antialiased_mode: str) -> None:
    """Render a scene at the given resolutions to PNG files (OUT/viewNNN_resX.XXX.png).

    Reads an anchor scene (PLY + weights, or a trained Scaffold-GS output), a container (leaves regenerated), or an
    INRIA 3DGS PLY (as plain 3DGS: SH colours, no gate). Views: the scene's stored cameras (a 3DGS PLY: its
    cameras.json's, else an orbit around it)."""
    from ..model import apply_antialiased_mode
    from ..scenes import load_any

    model = on_device(load_any(scene))
    apply_antialiased_mode(model, antialiased_mode)
    if background is not None:
        model.background = background
    render_views(model, parse_resolutions(res), Path(out_dir), list(views) or None, backend,
                 supersample=supersample)


@click.command()
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False), default="proxycodec-demo", show_default=True)
@click.option("--res", "res", default="1.0,0.3,0.1", show_default=True, help="Resolution ratios to render.")
@click.option("--backend", default="auto", show_default=True, type=click.Choice(["auto", "reference", "cpu", "cuda"]))
@click.option("--predictor-iters", default=None, type=int, help="Predictor fitting iterations [default: encode's].")
@click.option("--predictor-context", default=None, type=int,
              help="Proxies the predictor sees per leaf [default: encode's].")
@user_errors
def demo(out_dir: str, res: str, backend: str, predictor_iters: int, predictor_context: int) -> None:
    """Run the whole pipeline on the built-in scene: build and save it (OUT/sample.ply + weights), encode it with
    encode's defaults (OUT/sample.pxc), print its stats, decode it and render original and decoded views at several
    resolutions (OUT/renders/*.png), side by side (OUT/contact_sheet.png), with the PSNR of each decoded view
    against the original (OUT/demo.json)."""
    from .. import codec
    from ..metrics import psnr
    from ..model import SceneModel
    from ..sample import sample_model
    from .sheets import contact_sheet

    out = Path(out_dir)
    resolutions = parse_resolutions(res)
    t0 = time.perf_counter()
    model = sample_model()
    ply, weights = model.save(out / "sample.ply")
    click.echo(f"built the sample scene: {model.scene.num_anchors} anchors in {time.perf_counter() - t0:.1f} s "
               f"-> {ply} ({ply.stat().st_size:,} B) + {weights.name} ({weights.stat().st_size:,} B)")
    model = SceneModel.load(ply)  # what a user would do: work from the files alone
    # encode's defaults, as a user's `proxycodec encode sample.ply` gets them: the scene has no stage-2 predictor, so
    # encode fits one on L_recon, measures it against the scene and keeps it (the built-in scene's decoder is set
    # analytically: distillation would only move it away from its design, SPEC section 6)
    knobs = {k: v for k, v in (("predictor_iters", predictor_iters), ("predictor_context", predictor_context))
             if v is not None}
    report = codec.encode(ply, out / "sample.pxc", progress=lambda m: click.echo(m, err=True),
                          device=command_device(), **knobs)
    s = codec.stats(report.path)
    click.echo(f"encoded -> {report.path}: {s['file_bytes']:,} B, {s['bits_per_anchor']:.1f} bits/anchor, "
               f"{s['ratio']:.1f}x smaller than PLY + weights; sections: "
               + ", ".join(f"{k} {v:,} B" for k, v in s["bytes_by_group"].items()))
    t0 = time.perf_counter()
    decoded = codec.decode(report.path)
    click.echo(f"decoded {decoded.scene.num_anchors} anchors (leaves regenerated) in {time.perf_counter() - t0:.2f} s")
    decoded.cameras = model.cameras
    model, decoded = on_device(model), on_device(decoded)
    rows = render_views(model, resolutions, out / "renders", [0, 3], backend, prefix="original_")
    rows_d = render_views(decoded, resolutions, out / "renders", [0, 3], backend, prefix="decoded_")
    from PIL import Image
    import numpy as np

    for a, b in zip(rows, rows_d):
        b["psnr_vs_original"] = psnr(np.asarray(Image.open(b["path"]), np.float32) / 255.0,
                                     np.asarray(Image.open(a["path"]), np.float32) / 255.0)
        click.echo(f"view {b['view']}  xi {b['xi']:5.3f}  decoded vs original PSNR {b['psnr_vs_original']:.2f} dB")
    paths = []
    for i in range(0, len(rows), len(resolutions)):  # per view: a row of originals, then a row of decoded
        paths += [r["path"] for r in rows[i:i + len(resolutions)]] + [r["path"] for r in rows_d[i:i + len(resolutions)]]
    sheet = contact_sheet(paths, out / "contact_sheet.png", columns=len(resolutions))
    with atomic_write(out / "demo.json", "w") as fh:
        json.dump({"encode": report.to_json(), "original": rows, "decoded": rows_d}, fh, indent=2)
    click.echo(f"contact sheet (rows: original, decoded per view) -> {sheet}")
