"""Mip-Splatting's multi-scale protocol (``proxycodec eval --protocol mip-splatting``): its ground truth, built in
mip-NeRF's arithmetic, and the evaluation over full, 1/2, 1/4 and 1/8 of the reference."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from proxycodec.errors import ProxycodecError
from proxycodec.formats.images import decode_image, multiscale_target, resize_image


def test_silhouette_block_follows_the_protocol_not_the_box_filter():
    # one opaque red pixel and three transparent black ones, on white: straight RGBA is averaged first
    # (r 0.25, alpha 0.25 -> PNG bytes 63, 63), then composited (63/255 * 63/255 + 192/255 = 0.8140 -> byte 207)
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[0, 0] = (255, 0, 0, 255)
    t = multiscale_target(rgba, 1, (1.0, 1.0, 1.0))
    assert t.shape == (1, 1, 3) and t.dtype == np.float32
    assert t[0, 0, 0] == np.float32(207 / 255.0)
    # the composited image box-filtered (our own targets) keeps the red channel at 1
    comp = rgba[..., :3] / 255.0 * rgba[..., 3:] / 255.0 + (1 - rgba[..., 3:] / 255.0)
    assert resize_image(comp.astype(np.float32), 1, 1)[0, 0, 0] == pytest.approx(1.0)


def test_opaque_images_are_truncated_means():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (16, 24, 3), dtype=np.uint8)
    for levels in (0, 1, 2, 3):
        t = multiscale_target(rgb, levels, (0.0, 0.0, 0.0))
        f = 2 ** levels
        mean = rgb.astype(np.float64).reshape(16 // f, f, 24 // f, f, 3).mean(axis=(1, 3)) / 255.0
        assert t.shape == (16 // f, 24 // f, 3)
        # 8 bits by truncation, twice (the PNG, then the loader): never above the mean, within 2 steps of it
        assert np.all(t <= mean + 1e-6) and np.all(t >= mean - 2.0 / 255 - 1e-6)
    assert np.array_equal(multiscale_target(rgb, 0, (0, 0, 0)) * 255, rgb.astype(np.float32))


def test_odd_sizes_cannot_be_halved():
    with pytest.raises(ProxycodecError, match="cannot be halved"):
        multiscale_target(np.zeros((6, 10, 3), np.uint8), 2, (0, 0, 0))


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    from conftest import write_corner_dataset
    from proxycodec.sample import sample_model

    root = tmp_path_factory.mktemp("ms")
    data = write_corner_dataset(root / "data", size=64)
    scene = root / "s.ply"
    sample_model().save(scene)
    return data, scene


def test_eval_protocol_mip_splatting(corner, tmp_path):
    from click.testing import CliRunner

    from proxycodec.cli.main import cli
    from proxycodec.formats.datasets import load_dataset

    data, scene = corner
    r = CliRunner().invoke(cli, ["eval", str(scene), str(data), "--protocol", "mip-splatting", "--views", "1",
                                 "--max-width", "64", "-o", str(tmp_path / "ev")])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert rep["protocol"] == "mip-splatting"
    assert [(d["xi"], d["width"]) for d in rep["per_resolution"]] == [(1.0, 64), (0.5, 32), (0.25, 16), (0.125, 8)]
    s = rep["summary"]
    assert s["resolutions_in_average"] == [1.0, 0.5, 0.25, 0.125]
    assert s["psnr_avg"] == pytest.approx(np.mean([d["psnr"] for d in rep["per_resolution"]]))
    assert s["drop_full_to_eighth"] == pytest.approx(s["psnr_100"] - s["psnr_125"])
    assert "Mip-Splatting's multi-scale protocol" in r.output
    # the targets are the protocol's, not ours: at 1/8 they differ at the silhouettes
    d = load_dataset(data, max_width=64)
    v = d.test_indices[0]
    ms = d.load_multiscale_target(v, 0.125).numpy()
    raw = decode_image(d.cameras[v].image_path)
    assert np.array_equal(ms, multiscale_target(raw, 3, d.background))
    assert ms.shape == tuple(d.load_image(v, 0.125).shape)


def test_eval_protocol_refusals(corner, tmp_path):
    from click.testing import CliRunner

    from proxycodec.cli.main import cli

    data, scene = corner
    base = ["eval", str(scene), str(data), "--protocol", "mip-splatting", "--views", "1"]
    r = CliRunner().invoke(cli, base + ["--max-width", "48", "-o", str(tmp_path / "a")])  # 64 -> 48: not 64 / 2^k
    assert r.exit_code == 2 and "image size / 2^k" in r.output and ".png" in r.output
    assert len(r.output.strip().splitlines()) == 1
    r = CliRunner().invoke(cli, base + ["--res", "1.0", "-o", str(tmp_path / "b")])
    assert r.exit_code == 2 and "--res cannot be combined" in r.output


def test_decode_image_keeps_straight_alpha(tmp_path):
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 200, 100
    p = tmp_path / "a.png"
    Image.fromarray(rgba, "RGBA").save(p)
    assert np.array_equal(decode_image(p), rgba)
