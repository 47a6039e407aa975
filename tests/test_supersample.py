"""Supersampled renders: ``render.render_supersampled`` and ``--supersample`` of ``render``, ``decode`` and ``eval``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from test_codec import FAST, tiny_model

from proxycodec.cli.main import cli
from proxycodec.errors import ProxycodecError
from proxycodec.render import RenderResult, check_supersample, render_supersampled

pytestmark = pytest.mark.usefixtures("one_thread")


class PixelCentres:
    """A model whose render is a known function of the pixel indices: x, y and x * y (alpha x / width)."""

    def __init__(self):
        self.calls = []

    def render(self, camera, xi=1.0, *, backend="auto", size=None):
        cam = camera.scaled(xi) if size is None else camera.sized(*size)
        self.calls.append((xi, cam.width, cam.height))
        y, x = torch.meshgrid(torch.arange(cam.height, dtype=torch.float64),
                              torch.arange(cam.width, dtype=torch.float64), indexing="ij")
        return RenderResult(image=torch.stack([x, y, x * y], -1), alpha=x / cam.width, projected=None)


@pytest.mark.parametrize("factor", [2, 3])
def test_each_output_pixel_is_the_mean_of_its_block(factor):
    model = PixelCentres()
    cam = tiny_model().cameras[0]  # 32 x 24
    r = render_supersampled(model, cam, 0.5, factor)
    small = cam.scaled(0.5)
    assert model.calls == [(factor * 0.5, small.width * factor, small.height * factor)]  # the embedding sees f xi
    assert r.image.shape == (small.height, small.width, 3) and r.alpha.shape == (small.height, small.width)
    # a block's mean of x is f j + (f - 1) / 2, of y likewise; x y separates over the block
    mx = factor * np.arange(small.width) + (factor - 1) / 2
    my = factor * np.arange(small.height) + (factor - 1) / 2
    want = np.stack(np.broadcast_arrays(mx[None, :], my[:, None], my[:, None] * mx[None, :]), -1)
    np.testing.assert_allclose(r.image.numpy(), want, rtol=1e-12)
    np.testing.assert_allclose(r.alpha.numpy(), np.broadcast_to(mx / (factor * small.width), want.shape[:2]),
                               rtol=1e-12)


def test_the_embedding_ratio_is_capped_where_the_range_ends():
    model = PixelCentres()
    cam = tiny_model().cameras[0]
    render_supersampled(model, cam, 1.0, 3)
    assert model.calls == [(2.0, 96, 72)]  # camera.XI_MAX


def test_an_anchor_scene_supersampled_is_its_large_render_box_filtered():
    model = tiny_model()
    cam = model.cameras[1]
    with torch.no_grad():
        plain = render_supersampled(model, cam, 0.5, 1)
        assert torch.equal(plain.image, model.render(cam, 0.5).image)  # factor 1: the plain render
        r = render_supersampled(model, cam, 0.5, 2)
        big = model.render(cam, 1.0, size=(32, 24)).image.double()
    want = big.reshape(12, 2, 16, 2, 3).permute(0, 2, 1, 3, 4).reshape(12, 16, 4, 3).mean(2)
    assert r.image.shape == (12, 16, 3) and torch.isfinite(r.image).all()
    torch.testing.assert_close(r.image.double(), want, rtol=0, atol=1e-6)
    assert r.projected.count > 0 and r.visible_anchor_index is not None  # the large render's, kept
    assert not torch.equal(r.image, plain.image)


@pytest.mark.parametrize("bad", [0, 9, 1.5, True, "2", None])
def test_bad_factors_are_our_error(bad):
    with pytest.raises(ProxycodecError, match="supersampling factor"):
        check_supersample(bad)
    with pytest.raises(ProxycodecError, match="supersampling factor"):
        render_supersampled(PixelCentres(), tiny_model().cameras[0], 0.5, bad)


def test_a_render_too_large_to_supersample_is_refused_before_rendering():
    from proxycodec.render import MAX_SUPERSAMPLED_SIDE

    class Asked(Exception):
        pass

    class Recorder:
        calls = []

        def render(self, camera, xi=1.0, *, backend="auto", size=None):
            self.calls.append((xi, size))
            raise Asked  # what would be rendered is all this test needs

    model = Recorder()
    cam = tiny_model().cameras[0].sized(4096, 3072)
    with pytest.raises(ProxycodecError, match="over 16384 a side"):
        render_supersampled(model, cam, 2.0, 3)  # 8192 x 6144, x3
    assert model.calls == []
    with pytest.raises(Asked):
        render_supersampled(model, cam, 1.0, 4)  # exactly the limit
    assert model.calls == [(2.0, (MAX_SUPERSAMPLED_SIDE, 12288))]


def test_cli_render_and_decode_supersample(tmp_path):
    from PIL import Image

    from proxycodec import codec

    model = tiny_model()
    ply, _ = model.save(tmp_path / "s.ply")
    r = CliRunner().invoke(cli, ["render", str(ply), "--res", "0.5", "--view", "0", "--supersample", "2",
                                 "-o", str(tmp_path / "r")])
    assert r.exit_code == 0, r.output
    png = np.asarray(Image.open(tmp_path / "r" / "view000_res0.500.png"))
    with torch.no_grad():
        want = render_supersampled(model, model.cameras[0], 0.5, 2).image
    assert png.shape == (12, 16, 3)
    assert np.abs(png.astype(int) - (want.clamp(0, 1).numpy() * 255 + 0.5).astype(int)).max() <= 1
    r = CliRunner().invoke(cli, ["render", str(ply), "--supersample", "0"])
    assert r.exit_code == 2 and "--supersample" in r.output

    pxc = tmp_path / "s.pxc"
    codec.encode(model, pxc, codec.EncodeConfig(**FAST))
    for factor in ("1", "2"):
        out = tmp_path / f"d{factor}"
        r = CliRunner().invoke(cli, ["decode", str(pxc), "--res", "0.5", "--view", "0", "--supersample", factor,
                                     "-o", str(out)])
        assert r.exit_code == 0, r.output
        assert np.asarray(Image.open(out / "view000_res0.500.png")).shape == (12, 16, 3)
    a, b = (np.asarray(Image.open(tmp_path / f"d{f}" / "view000_res0.500.png")).astype(int) for f in "12")
    assert not np.array_equal(a, b)
    decoded = codec.decode(pxc)  # decode --supersample 2 is the decoded scene's supersampled render
    with torch.no_grad():
        want = render_supersampled(decoded, decoded.cameras[0], 0.5, 2).image
    assert np.abs(b - (want.clamp(0, 1).numpy() * 255 + 0.5).astype(int)).max() <= 1
