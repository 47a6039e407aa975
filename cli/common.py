"""What the commands share: one-line user errors, option parsing, config defaults, writing rendered views."""

from __future__ import annotations

import dataclasses
import functools
import importlib
import os
import sys
import time
from pathlib import Path

import click

from ..errors import ProxycodecError
from ..processes import terminated


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
        except KeyboardInterrupt as e:
            if terminated(e):
                click.echo("terminated (SIGTERM)", err=True)
                sys.exit(143)
            click.echo("interrupted", err=True)
            sys.exit(130)

    return wrapper


def set_device(name: str) -> None:
    """The group's ``--device``: recorded for the commands (and child processes) in ``$PROXYCODEC_DEVICE``; an
    explicit ``cuda`` is checked at once, so a machine without a GPU gets one line and exit 2 whatever the command."""
    from ..devices import CUDA, ENV, name_from_env, resolve

    os.environ[ENV] = name
    try:
        if name_from_env() == CUDA:  # the name checked there, as any child process reads it
            resolve(CUDA)
    except ProxycodecError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)


def command_device():
    """The ``torch.device`` the running command computes on (``--device``, resolved)."""
    from ..devices import resolve

    return resolve()


def on_device(model):
    """``model`` (a scene loaded by ``scenes.load_any``) on the command's device; the torch-free lite scenes have
    no device and stay as they are."""
    return model.to(command_device()) if hasattr(model, "to") else model


def parse_resolutions(text: str) -> list[float]:
    from ..camera import check_xi

    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ProxycodecError(f"--res expects comma-separated numbers, got {text!r}") from None
    if not vals:
        raise ProxycodecError("--res is empty")
    return [check_xi(v) for v in vals]


class Background(click.ParamType):
    """``--background``: ``auto`` (None: the scene's own), ``black``, ``white`` or ``R,G,B`` in [0, 1]."""

    name = "auto|black|white|R,G,B"
    NAMED = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}

    def convert(self, value, param, ctx):
        if value is None or isinstance(value, tuple):
            return value
        text = str(value).strip().lower()
        if text == "auto":
            return None
        if text in self.NAMED:
            return self.NAMED[text]
        try:
            rgb = tuple(float(x) for x in text.split(","))
        except ValueError:
            rgb = ()
        if len(rgb) != 3 or not all(0.0 <= x <= 1.0 for x in rgb):
            self.fail(f"{value!r} is not auto, black, white or three numbers in [0, 1] (R,G,B)", param, ctx)
        return rgb


def background_option(auto_help: str):
    """``--background`` (default ``auto``: ``auto_help`` says what that is for the command)."""
    return click.option("--background", type=Background(), default="auto", show_default=True,
                        help=f"Background colour: black, white or R,G,B in [0, 1]; auto: {auto_help}.")


def supersample_option(f):
    """``--supersample N``: render at N times the size and box-filter down (``render.render_supersampled``)."""
    from ..render import MAX_SUPERSAMPLE

    return click.option("--supersample", type=click.IntRange(1, MAX_SUPERSAMPLE), default=1, show_default=True,
                        help="Anti-alias by supersampling: render at N times the width and height (the resolution "
                             "embedding sees N x the ratio) and average each N x N block; 1: the plain render. "
                             "Small sizes gain most, at little cost (benchmarks/README.md, 'Supersampling').")(f)


#: ``--antialiased`` / ``--source-antialiased`` (``model.antialiased_override``; kept here: building the command line
#: imports no torch).
ANTIALIASED_CHOICES = ("scene", "on", "off")


def antialiased_option(what: str):
    """``--antialiased scene|on|off``: the antialiased filter's opacity compensation for ``what`` renders
    (``model.apply_antialiased_mode``)."""
    return click.option(
        "--antialiased", "antialiased_mode", type=click.Choice(ANTIALIASED_CHOICES), default="scene",
        show_default=True,
        help=f"The antialiased filter's opacity compensation (gsplat's antialiased mode, Mip-Splatting's 2D filter) "
             f"when {what} renders: the scene's own setting (an anchor scene's decoder; the flag of an SPZ or GLB; an "
             f"INRIA PLY has none: 'on' for a gsplat PLY trained antialiased), or forced on or off.")


class ConfigDefault(click.Option):
    """An option whose default is a field of a configuration dataclass (``config``: "module:Class"; ``field``: the
    option's name unless given; ``convert``: field value -> option value). The class is imported when click first
    needs the default (the command's ``--help`` or a run), so building the command line imports no torch."""

    def __init__(self, *args, config: str, field: str | None = None, convert=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.config, self.field, self.convert = config, field or self.name, convert

    def get_default(self, ctx, call=True):
        value = ctx.lookup_default(self.name, call=call)
        if value is not None:
            return value
        module, _, name = self.config.partition(":")
        f = getattr(importlib.import_module(module), name).__dataclass_fields__[self.field]
        value = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        return value if self.convert is None else self.convert(value)


def config_option(config: str, *param_decls: str, field: str | None = None, convert=None, **attrs):
    """``click.option`` with its default from ``config``'s field (:class:`ConfigDefault`); give ``type``."""
    return click.option(*param_decls, cls=ConfigDefault, config=config, field=field, convert=convert, **attrs)


def render_views(model, resolutions, out_dir: Path, views, backend: str, prefix: str = "",
                 supersample: int = 1) -> list[dict]:
    """Render and write PNGs. ``model``: a ``SceneModel`` or a ``lite.LiteScene`` (torch-free: numpy images; the
    plain render only), supersampled by ``supersample`` (``render.render_supersampled``)."""
    from PIL import Image

    from ..render import render_supersampled

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
            r = render_supersampled(model, cams[i], xi, supersample, backend=backend)
            dt = time.perf_counter() - t0
            h, w = r.image.shape[:2]
            path = out_dir / f"{prefix}view{i:03d}_res{xi:.3f}.png"
            from ..fileio import atomic_write

            with atomic_write(path) as fh:
                Image.fromarray(_image_to_uint8(r.image)).save(fh, format="PNG")
            rows.append({"view": i, "xi": xi, "width": w, "height": h, "gaussians": r.projected.count,
                         # an INRIA PLY's render (explicit Gaussians) has no anchors
                         "anchors_visible": len(getattr(r, "visible_anchor_index", ())), "seconds": dt,
                         "path": str(path)})
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
