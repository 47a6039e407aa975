"""``proxycodec`` command line: a thin click layer over the library API.

Every user error becomes one line on stderr and exit status 2 (no traceback); an interrupt exits 130, SIGTERM 143,
both after what Ctrl-C keeps is kept (a training run's checkpoint).
The commands live in sibling modules (plain ``click`` commands); this module makes the group and registers them.
"""

from __future__ import annotations

import click

from .. import __version__
from ..devices import CHOICES as DEVICE_CHOICES
from ..devices import ENV as DEVICE_ENV
from ..processes import stop_on_sigterm
from ..threads import ENV as THREADS_ENV
from ..threads import set_threads
from .batch import batch
from .bench import bench
from .codec import decode, encode, stats
from .commands import demo, render, sample
from .common import set_device
from .convert import convert
from .fit import eval_cmd, fit
from .view import view  # imports viser only when the command runs


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="proxycodec")
@click.option("--threads", type=click.IntRange(min=1), default=None, envvar=THREADS_ENV, show_envvar=True,
              help="Threads for the CPU work of torch [default: the cores this process may run on].")
@click.option("--device", metavar="[" + "|".join(DEVICE_CHOICES) + "]", default="auto", envvar=DEVICE_ENV,
              show_envvar=True, show_default=True,
              help="Where training, encoding and torch rendering compute: auto is cuda when torch sees a GPU and "
                   "gsplat imports, else cpu. decode renders without torch, on the CPU, unless --device cuda.")
def cli(threads: int | None, device: str) -> None:
    """proxycodec: compress anchor-based 3D Gaussian Splatting scenes to compact proxy anchors and render them
    at any resolution."""
    set_threads(threads)
    set_device(device)


for _command in (sample, render, demo, fit, convert, encode, decode, stats, eval_cmd, bench, batch, view):
    cli.add_command(_command)


def main() -> None:
    stop_on_sigterm()
    cli(prog_name="proxycodec")
