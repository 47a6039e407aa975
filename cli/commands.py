"""Commands beyond the basics; each registers on the ``cli`` group."""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from .main import cli, parse_resolutions, render_views, user_errors


@cli.command()
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False), default="proxycodec-demo", show_default=True)
@click.option("--res", "res", default="1.0,0.3,0.1", show_default=True, help="Resolution ratios to render.")
@click.option("--backend", default="auto", show_default=True, type=click.Choice(["auto", "reference", "cpu", "cuda"]))
@user_errors
def demo(out_dir: str, res: str, backend: str) -> None:
    """Run the main job on the built-in scene: build it, save it, render it at several resolutions."""
    from ..model import SceneModel
    from ..sample import sample_model
    from .sheets import contact_sheet

    out = Path(out_dir)
    t0 = time.perf_counter()
    model = sample_model()
    ply, weights = model.save(out / "sample.ply")
    click.echo(f"built the sample scene: {model.scene.num_anchors} anchors in {time.perf_counter() - t0:.1f} s "
               f"-> {ply} ({ply.stat().st_size:,} B) + {weights.name} ({weights.stat().st_size:,} B)")
    model = SceneModel.load(ply)  # what a user would do: render from the files alone
    rows = render_views(model, parse_resolutions(res), out / "renders", [0, 3], backend)
    sheet = contact_sheet([r["path"] for r in rows], out / "contact_sheet.png", columns=len(parse_resolutions(res)))
    (out / "demo.json").write_text(json.dumps(rows, indent=2))
    click.echo(f"contact sheet -> {sheet}")
