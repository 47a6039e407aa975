"""``proxycodec view``: a local web viewer of a scene (a thin layer over ``proxycodec.viewer``; needs viser)."""

from __future__ import annotations

import time

import click

from .common import user_errors


@click.command()
@click.argument("source", type=click.Path())
@click.option("--port", type=click.IntRange(1, 65535), default=8080, show_default=True,
              help="Port to serve on (the next free one if taken).")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="Address to listen on (0.0.0.0: every interface; the viewer has no authentication).")
@click.option("--res", type=float, default=1.0, show_default=True,
              help="Initial resolution ratio of the slider, in [0.025, 2.0] (of the browser viewport's pixels).")
@user_errors
def view(source: str, port: int, host: str, res: float) -> None:
    """Open SOURCE (a container, an anchor scene, a 3DGS PLY, SPZ or GLB) in a local web viewer; runs until Ctrl-C.

    The server renders each view with proxycodec's own renderer (view-dependent MLP colours, the coverage gate at
    the chosen resolution) and streams it to the browser; a slider sets the resolution ratio (the image is shown
    upscaled, nearest, so what a resolution looks like is what you see). Needs viser: pip install -e '.[view]'."""
    from ..viewer import import_viser, start_viewer

    import_viser()  # before loading anything: a missing viser is one line
    viewer = start_viewer(source, host=host, port=port, res=res, log=click.echo)
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        click.echo("stopping", err=True)
    finally:
        viewer.stop()
