"""``proxycodec bench``: the size / quality / time trade-off of the encode settings on a user's own fitted scene."""

from __future__ import annotations

import click

from .common import config_option, user_errors


@click.command()
@click.argument("scene", type=click.Path(dir_okay=False))
@click.argument("dataset", type=click.Path(file_okay=False))
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Results folder [default: SCENE's name + '_bench'].")
@click.option("--quick", is_flag=True, help="2-3 settings per sweep and 2 test views (a smoke run).")
@click.option("--views", type=int, default=None, help="Test views evaluated per point [default: 8; 2 with --quick].")
@click.option("--max-width", type=int, default=None,
              help="100% reference width [default: the one the scene was fit at].")
@click.option("--test-every", type=int, default=8, show_default=True, help="COLMAP: every N-th image is a test view.")
@click.option("--sweeps", default=None,
              help="Comma-separated subset of proxy_ratio, leaf_sample, bits, zstd_level, predictor_blocks, entropy, "
                   "positions [default: all].")
@click.option("--in-process", is_flag=True,
              help="Run every step in this process (faster start; peak RSS is then the whole run's, not per step).")
@click.option("--fresh", is_flag=True, help="Ignore the results of an earlier run in the folder (default: resume).")
@click.option("--any-code", is_flag=True,
              help="Reuse the steps an earlier run recorded with other code too (default: a step whose code changed "
                   "runs again).")
@click.option("--predictor-iters", type=int, default=None,
              help="Encode-time predictor iterations at every point [default: encode's default, 2000].")
@click.option("--distill-iters", type=int, default=None,
              help="Distillation iterations of the default point, for a scene without a stage-2 predictor "
                   "[default: encode's default].")
@config_option("proxycodec.codec:EncodeConfig", "--seed", type=int, show_default=True,
               help="Encode seed (proxy selection, predictor).")
@click.option("--backend", default="auto", show_default=True, type=click.Choice(["auto", "reference", "cpu", "cuda"]))
@user_errors
def bench(scene, dataset, out_dir, quick, views, max_width, test_every, sweeps, in_process, fresh, any_code,
          predictor_iters, distill_iters, seed, backend) -> None:
    """Sweep the encode settings (proxy ratio, leaf sample fraction, quantisation bits, zstd level, predictor depth)
    on SCENE (an anchor PLY + weights, e.g. from `proxycodec fit`) and evaluate every container on DATASET's test
    views: bytes, PSNR/SSIM over ten resolutions, encode/decode/render times, peak RSS per step. Writes
    results.json, bench.md and PNG plots (PSNR vs bytes with the Pareto front, PSNR vs time, render time vs
    resolution) in OUT; an interrupted run resumes where it stopped.

    The default point is `proxycodec encode SCENE` as a user runs it (a scene with a stage-2 predictor: used as
    fitted; without one: the measured choice between the L_recon predictor and distillation). Every other point
    refits the predictor on L_recon alone, so that the knobs are compared at equal cost."""
    from pathlib import Path

    from ..bench import run_bench
    from ..errors import ProxycodecError

    if views is not None and views < 1:
        raise ProxycodecError("--views must be >= 1")
    out = out_dir or str(Path(scene).with_name(Path(scene).stem + "_bench"))
    paths = run_bench(scene, dataset, out, quick=quick, views=views, max_width=max_width, test_every=test_every,
                      sweeps=[s.strip() for s in sweeps.split(",") if s.strip()] if sweeps else None,
                      isolate=not in_process, fresh=fresh, any_code=any_code, backend=backend,
                      predictor_iters=predictor_iters, distill_iters=distill_iters, seed=seed,
                      log=lambda s: click.echo(s, err=True))
    click.echo(Path(paths["markdown"]).read_text())
    click.echo("wrote " + ", ".join(str(p) for p in paths.values()))
