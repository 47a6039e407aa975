"""The pipeline on a device (``--device``, ``device=``): every test runs on the CPU and, where a CUDA GPU and gsplat
are present, on ``cuda`` too (the ``cuda`` marker skips it elsewhere with the reason). On the CPU each one checks
that passing the device changes nothing; on CUDA, that the same steps run there and give the CPU's result within
float tolerances (gsplat's backward accumulates with atomics, so CUDA runs are not bitwise reproducible)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import write_corner_dataset
from test_codec import FAST, tiny_model
from test_convert import _ball, _tiny_config

from proxycodec import codec
from proxycodec.devices import as_device
from proxycodec.formats.images import resize_image
from proxycodec.loop import TargetImages, resize_torch, resize_weights
from proxycodec.metrics import psnr

pytestmark = pytest.mark.usefixtures("one_thread")

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from proxycodec.formats.datasets import load_dataset

    return load_dataset(write_corner_dataset(tmp_path_factory.mktemp("tiny_blender"), 32))


def _img(t) -> np.ndarray:
    return t.detach().clamp(0, 1).cpu().numpy()


# ------------------------------------------------------------------------------------------------ targets
@pytest.mark.parametrize("src,dst", [((64, 48), (32, 24)), ((64, 48), (19, 13)), ((50, 37), (7, 5)),
                                     ((32, 24), (32, 24)), ((20, 16), (33, 27))])
def test_resize_on_the_device_is_the_datasets_filter(src, dst):
    """``resize_torch`` (targets made where training runs) applies PIL's own weights: BOX down, BICUBIC up."""
    rgb = np.random.default_rng(0).random((src[1], src[0], 3)).astype(np.float32)
    want = resize_image(rgb, *dst)
    got = resize_torch(torch.from_numpy(rgb), *dst).numpy()
    assert got.shape == want.shape
    assert np.abs(got - want).max() < 2e-6
    w = resize_weights(src[0], dst[0])
    assert np.allclose(w.sum(1), 1.0) and (w >= 0).all() == (dst[0] <= src[0])


def test_targets_on_the_cpu_are_the_pil_path(data):
    a, b = TargetImages(data, 1 << 30), TargetImages(data, 1 << 30, "cpu")
    for xi in (0.3, 0.77, 1.0):
        assert torch.equal(a.get(1, xi), b.get(1, xi))


@pytest.fixture
def device_branches(monkeypatch):
    """The code a CUDA run takes (targets cached and resized as tensors, teacher renders kept as tensors), run here
    on CPU tensors: the modules' test of "not the CPU" made to answer yes."""
    import proxycodec.distill
    import proxycodec.loop

    monkeypatch.setattr(proxycodec.loop, "CPU", "no such device")
    monkeypatch.setattr(proxycodec.distill, "CPU", "no such device")


def test_the_device_branch_of_the_targets_gives_the_cpu_s_targets(data, device_branches):
    t = TargetImages(data, 1 << 30, "cpu")
    ref = t.reference(1)
    assert isinstance(ref, torch.Tensor) and ref.dtype == torch.float16  # cached as a tensor, not numpy
    for xi in (0.3, 0.77, 1.0):
        want = torch.from_numpy(resize_image(data.load_image(1, 1.0).numpy().astype(np.float16).astype(np.float32),
                                             *data.image_size(1, xi)))
        assert (t.get(1, xi) - want).abs().max() < 2e-6


@pytest.mark.parametrize("rule", ["full", "whole"])
def test_the_device_branch_of_a_teacher_s_targets_and_a_distillation(device_branches, rule):
    from proxycodec.camera import orbit_cameras
    from proxycodec.distill import TeacherViews, distill
    from proxycodec.model import SceneModel
    from proxycodec.train import FitConfig

    m = tiny_model(150, 3)
    m = SceneModel(m.scene, m.decoder, orbit_cameras((0.0, 0.0, 0.1), 1.5, 10, width=32, height=24), m.background)
    views = TeacherViews(m, m.cameras, targets=rule)
    want = views.render(2, views.source_size(2, 13, 10))
    got = views.targets(1 << 30).get(2, 13 / 32)
    assert isinstance(got, torch.Tensor) and got.shape == (10, 13, 3)
    ref = torch.from_numpy(resize_image(want, 13, 10) if want.shape[:2] != (10, 13) else want)
    assert (got - ref).abs().max() < 2e-3  # the 100% render cached in float16 ("full"), or rendered at its size
    assert isinstance(views.load_image(2, 0.5), torch.Tensor)
    cfg = FitConfig(iters=4, predictor_hidden=16, predictor_blocks=1, predictor_warmup=2, log_every=1e9, seed=0)
    res = distill(m, cfg, views=views, log=lambda s: None)
    assert res.iterations == 4 and torch.isfinite(res.model.scene.features).all()


# ------------------------------------------------------------------------------------------------ the pipeline
@pytest.mark.parametrize("device", DEVICES)
def test_a_fit_runs_on_the_device(data, tmp_path, device):
    from proxycodec.train import FitConfig, fit

    cfg = FitConfig(iters=24, max_width=None, init_points=250, update_interval=8, predictor_warmup=5,
                    predictor_hidden=16, predictor_blocks=1, checkpoint_every=0, log_every=1e9, seed=3,
                    stage2_start=0.5)
    on = fit(data, tmp_path / "on.ply", cfg, dataset_root="tiny", log=lambda s: None, device=device)
    assert on.model.device.type == as_device(device).type and on.model.scene.positions.device == on.model.device
    ref = fit(data, tmp_path / "ref.ply", cfg, dataset_root="tiny", log=lambda s: None)
    assert on.iterations == ref.iterations == 24
    cam = data.cameras[data.test_indices[0]]
    a = _img(on.model.render(cam, 1.0).image)
    b = _img(ref.model.render(cam, 1.0).image)
    if device == "cpu":
        assert (tmp_path / "on.ply").read_bytes() == (tmp_path / "ref.ply").read_bytes()
    else:
        assert np.isfinite(a).all() and psnr(a, b) > 25


@pytest.mark.parametrize("device", DEVICES)
def test_a_plain_3dgs_fit_runs_on_the_device(data, device):
    from proxycodec.explicit import ExplicitConfig, ExplicitModel, train_explicit

    cfg = ExplicitConfig(iters=20, max_width=None, init_points=300, log_every=1e9, seed=1)
    on = train_explicit(data, cfg, None, device=device)
    ref = train_explicit(data, cfg, None)
    assert on.n_gaussians == ref.n_gaussians or device != "cpu"
    cam = data.cameras[data.test_indices[0]]
    a = _img(ExplicitModel(on).to(device).render(cam).image)
    b = _img(ExplicitModel(ref).render(cam).image)
    assert (a == b).all() if device == "cpu" else psnr(a, b) > 25


@pytest.mark.parametrize("device", DEVICES)
def test_encode_with_distillation_and_decode_on_the_device(tmp_path, device):
    from test_distill import QUICK

    m = tiny_model(200, 1)
    knobs = dict(QUICK, distill_iters=6, distill_views=10, entropy="model", entropy_iters=20)
    on = codec.encode(m, tmp_path / "on.pxc", device=device, **knobs)
    codec.encode(m, tmp_path / "ref.pxc", **knobs)
    assert on.meta["distill"]["iterations"] == 6
    dec = codec.decode(tmp_path / "on.pxc").to(device)
    cam = (m.cameras or codec.default_cameras(m))[0]
    a = _img(dec.render(cam, 0.5).image)
    b = _img(codec.decode(tmp_path / "ref.pxc").render(cam, 0.5).image)
    if device == "cpu":
        assert (tmp_path / "on.pxc").read_bytes() == (tmp_path / "ref.pxc").read_bytes()
    else:
        assert np.array_equal(a, _img(on.model.to(device).render(cam, 0.5).image))  # the report's model is decode's
        assert psnr(a, b) > 30


@pytest.mark.parametrize("device", DEVICES)
def test_the_conversion_starts_on_the_device(tmp_path, device):
    from proxycodec.convert import auto_views, initial_model, load_gaussians

    g = load_gaussians(_ball(300))
    cfg = _tiny_config()
    cams, _ = auto_views(g, 8, 32)
    on, _ = initial_model(g, cfg, cams, lambda s: None, device=device)
    ref, _ = initial_model(g, cfg, cams, lambda s: None)
    assert on.device.type == as_device(device).type
    a, b = _img(on.render(cams[0]).image), _img(ref.render(cams[0]).image)
    assert (a == b).all() if device == "cpu" else psnr(a, b) > 30


@pytest.mark.parametrize("device", DEVICES)
def test_features_are_queried_on_the_device(tmp_path, device):
    from proxycodec.query import query_features

    m = tiny_model(200, 2)
    codec.encode(m, tmp_path / "s.pxc", **FAST)
    pts = np.random.default_rng(0).uniform(-0.3, 0.3, (50, 3)).astype(np.float32)
    a = query_features(tmp_path / "s.pxc", pts, 0.5, device=device)
    b = query_features(tmp_path / "s.pxc", pts, 0.5)
    assert np.array_equal(a, b) if device == "cpu" else np.allclose(a, b, atol=1e-4)


def test_models_move_between_devices_as_copies():
    m = tiny_model(50, 0)
    assert m.to("cpu") is m  # already there: itself
    assert m.device == torch.device("cpu")
