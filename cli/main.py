"""``proxycodec`` command line: a thin click layer over the library API.

Every user error becomes one line on stderr and exit status 2 (no traceback); an interrupt exits 130.
Command groups live in sibling modules and register themselves on ``cli`` when imported below.
"""

from __future__ import annotations

import functools
import sys
import time
from pathlib import Path

import click

from .. import __version__
from ..errors import ProxycodecError

RESOLUTIONS = (1.0, 0.5, 0.25, 0.1)


def user_errors(fn):
    """Turn the library's one exception type (and OS errors on user paths) into a one-line message."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ProxycodecError as e:
            click.echo(f"error: {e}", err=True)
            sys.exit(2)
        except (FileNotFoundError, IsADirectoryError, PermissionError) as e:
            click.echo(f"error: {e.filename}: {e.strerror}", err=True)
            sys.exit(2)
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            sys.exit(130)

    return wrapper


def parse_resolutions(text: str) -> list[float]:
    from ..camera import check_xi

    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ProxycodecError(f"--res expects comma-separated numbers, got {text!r}") from None
    if not vals:
        raise ProxycodecError("--res is empty")
    return [check_xi(v) for v in vals]


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="proxycodec")
def cli() -> None:
    """proxycodec: compress anchor-based 3D Gaussian Splatting scenes to compact proxy anchors and render them
    at any resolution."""


@cli.command()
@click.argument("out", type=click.Path(dir_okay=False), default="sample.ply")
@click.option("--seed", default=0, show_default=True, help="Seed of the procedural scene.")
@user_errors
def sample(out: str, seed: int) -> None:
    """Write the built-in procedural scene as an anchor PLY (weights beside it as OUT.weights.pxc)."""
    from ..sample import sample_model

    model = sample_model(seed)
    ply, weights = model.save(out)
    click.echo(f"wrote {ply} ({model.scene.num_anchors} anchors) and {weights}")


@cli.command()
@click.argument("scene", type=click.Path(dir_okay=False))
@click.option("--res", "res", default="1.0,0.5,0.25,0.1", show_default=True,
              help="Comma-separated resolution ratios in [0.025, 2.0].")
@click.option("-o", "--out", "out_dir", type=click.Path(file_okay=False), default="renders", show_default=True)
@click.option("--view", "views", multiple=True, type=int, help="Camera index (repeatable; default: all stored).")
@click.option("--backend", default="auto", show_default=True,
              type=click.Choice(["auto", "reference", "cpu", "cuda"]), help="Compositing backend.")
@user_errors
def render(scene: str, res: str, out_dir: str, views: tuple[int, ...], backend: str) -> None:
    """Render an anchor scene (PLY + weights) at the given resolutions to PNG files."""
    from ..model import SceneModel

    model = SceneModel.load(scene)
    render_views(model, parse_resolutions(res), Path(out_dir), list(views) or None, backend)


def render_views(model, resolutions, out_dir: Path, views, backend: str, prefix: str = "") -> list[dict]:
    """Render and write PNGs. ``model``: a ``SceneModel`` or a ``lite.LiteScene`` (torch-free: numpy images)."""
    from PIL import Image

    cams = model.cameras
    if not cams:
        from ..sample import sample_cameras

        cams = sample_cameras()
    idx = views if views is not None else list(range(len(cams)))
    for i in idx:
        if not 0 <= i < len(cams):
            raise ProxycodecError(f"view {i} does not exist (the scene has {len(cams)} cameras)")
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for i in idx:
        for xi in resolutions:
            t0 = time.perf_counter()
            r = model.render(cams[i], xi, backend=backend)
            dt = time.perf_counter() - t0
            h, w = r.image.shape[:2]
            path = out_dir / f"{prefix}view{i:03d}_res{xi:.3f}.png"
            from ..fileio import atomic_write

            with atomic_write(path) as fh:
                Image.fromarray(_image_to_uint8(r.image)).save(fh, format="PNG")
            rows.append({"view": i, "xi": xi, "width": w, "height": h, "gaussians": r.projected.count,
                         "anchors_visible": len(r.visible_anchor_index), "seconds": dt, "path": str(path)})
            click.echo(f"view {i:3d}  xi {xi:5.3f}  {w:4d}x{h:<4d}  {r.projected.count:7d} Gaussians  "
                       f"{dt * 1000:7.1f} ms  -> {path}")
    return rows


def _image_to_uint8(image):
    """A rendered image (a torch tensor, or a numpy array from the torch-free path) -> [H, W, C] uint8."""
    if type(image).__module__ == "numpy":  # no torch import for the torch-free path
        from ..lite import image_to_uint8
    else:
        from ..model import image_to_uint8
    return image_to_uint8(image)


def main() -> None:
    cli(prog_name="proxycodec")


# Command modules register themselves on ``cli``.
from . import commands  # noqa: E402,F401
from . import bench  # noqa: E402,F401
