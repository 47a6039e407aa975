"""``proxycodec convert``: an INRIA 3DGS PLY -> an anchor scene, without images (a thin layer over
``proxycodec.convert``)."""

from __future__ import annotations

import functools
import json

import click

from .common import ANTIALIASED_CHOICES, background_option, command_device, config_option, user_errors

convert_option = functools.partial(config_option, "proxycodec.convert:ConvertConfig")

def convert_options(fn):
    """The options ``convert`` shares with ``encode`` of a 3DGS PLY."""
    for opt in reversed([
        convert_option("--voxel-size", type=float, show_default=True,
                       help="Anchor voxel size in world units (0: chosen from the Gaussians' weight per cell)."),
        convert_option("--max-anchors", type=click.IntRange(1), default=None,
                       help="At most this many anchors (default: as many as the Gaussians' weight per cell asks)."),
        convert_option("--target-size", type=click.IntRange(1), default=None,
                       help="Aim the container at about this many bytes (sets the anchor budget; measured in "
                            "benchmarks/README.md, 'Anchor budgets')."),
        convert_option("--views", "views", type=int, show_default=True,
                       help="Automatic teacher views when no cameras.json sits beside the PLY."),
        convert_option("--view-size", type=int, show_default=True, help="Their width and height in pixels."),
        background_option("the one the PLY was trained on: white_background in the trainer's cfg_args beside it "
                          "(or two folders up), else black, the 3DGS trainers' default; the anchor scene keeps it"),
        click.option("--max-width", type=int, default=800, show_default=True,
                     help="Teacher views from cameras.json are downscaled to this width."),
        click.option("--source-antialiased", type=click.Choice(ANTIALIASED_CHOICES), default="scene",
                     show_default=True,
                     help="Render the source with the antialiased filter's opacity compensation (gsplat's antialiased "
                          "mode, Mip-Splatting's 2D filter): as the file says (an SPZ's or GLB's flag; an INRIA PLY "
                          "has none: 'on' for a gsplat PLY trained antialiased), or forced on or off."),
    ]):
        fn = opt(fn)
    return fn


def make_config(iters, time_budget, seed, voxel_size, views, view_size, background, max_width, max_anchors=None,
                target_size=None, lambda_rate=None, checkpoint_every=None, source_antialiased="scene"):
    from ..convert import ConvertConfig, replace_fit
    from ..model import antialiased_override

    cfg = ConvertConfig(voxel_size=voxel_size, views=views, view_size=view_size, background=background,
                        max_anchors=max_anchors, target_size=target_size,
                        source_antialiased=antialiased_override(source_antialiased))
    run = {"max_width": max_width, "seed": seed}
    if iters is not None or time_budget is not None:
        run.update(iters=iters, time_budget=time_budget)
    if lambda_rate is not None:
        run["lambda_rate"] = lambda_rate
    if checkpoint_every is not None:
        run["checkpoint_every"] = checkpoint_every
    return replace_fit(cfg, **run)


@click.command()
@click.argument("ply", type=click.Path(dir_okay=False))
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False),
              help="Anchor PLY to write (weights go beside it as OUT.weights.pxc).")
@click.option("--iters", type=int, default=None, help="Training iterations [default: 4000 without --time-budget].")
@click.option("--time-budget", type=float, default=None,
              help="Seconds of training steps (the renderer's warm-up excluded); schedules follow elapsed time.")
@click.option("--seed", type=int, default=0, show_default=True)
@convert_options
@convert_option("--lambda-rate", field="fit", convert=lambda fit: fit.lambda_rate, type=click.FloatRange(0.0),
                show_default=True,
                help="Weight of the rate term in training (as fit --lambda-rate; 0: off). On bonsai's 300k-Gaussian "
                     "PLY, 0 gave a 54% larger container for +0.49 dB against the source (benchmarks/README.md, "
                     "'The rate term in conversion').")
@click.option("--resume", is_flag=True, help="Continue from OUT's checkpoint (OUT.ckpt.pxc).")
@convert_option("--checkpoint-every", field="fit", convert=lambda fit: fit.checkpoint_every,
                type=click.FloatRange(0.0), show_default=True,
                help="Seconds of training between checkpoints (0: only when stopped: Ctrl-C, SIGTERM, an error).")
@click.option("--json", "as_json", is_flag=True, help="Print the conversion report as JSON on stdout.")
@user_errors
def convert(ply, out, iters, time_budget, seed, voxel_size, max_anchors, target_size, views, view_size, background,
            max_width, source_antialiased, lambda_rate, resume, checkpoint_every, as_json) -> None:
    """Turn an INRIA 3DGS PLY (SH degree 0..3; the reference trainer's, splatfacto's, an app's export) into a
    resolution-aware anchor scene, trained against the PLY's own renders: no images needed. Writes OUT (anchor PLY)
    and OUT.weights.pxc (MLPs, proxies and their stage-2 predictor: `encode OUT` uses them as they are); OUT.ckpt.pxc
    while training (--resume). The source renders on --background (default: the one it was trained on).

    Views: the PLY's cameras.json when it has one (beside it, or two folders up as 3DGS writes it), else automatic
    views around (objects) or inside (rooms) the scene. Progress lines show the run; `proxycodec encode OUT` then
    compresses the result (or `proxycodec encode PLY` does both)."""
    from ..convert import convert as run

    cfg = make_config(iters, time_budget, seed, voxel_size, views, view_size, background, max_width, max_anchors,
                      target_size, lambda_rate, checkpoint_every, source_antialiased)
    r = run(ply, out, cfg, resume=resume, log=lambda m: click.echo(m, err=True), device=command_device())
    if as_json:
        click.echo(json.dumps(r.to_json(), indent=2))
    else:
        click.echo(f"wrote {r.path} ({r.model.scene.num_anchors:,} anchors) in {r.seconds['total']:.0f} s; held-out "
                   f"PSNR vs the source's anti-aliased renders {r.report['converted']['psnr']:.2f} dB")
