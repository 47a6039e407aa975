"""Training (``proxycodec fit``), evaluation (``proxycodec eval``) and the metrics they use.

A tiny Blender-format dataset is written once per module: part of the built-in sample scene (the box on its patch of
floor) rendered from 8 + 2 orbit cameras at 32x32 px. Fits run a few dozen iterations with small schedules.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import read_until, signal_when_ready, write_corner_dataset

from proxycodec.errors import ProxycodecError
from proxycodec.metrics import dssim, mse_to_psnr, psnr, ssim, ssim_torch

SIZE = 32


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory) -> Path:
    return write_corner_dataset(tmp_path_factory.mktemp("tiny_blender"), SIZE)


@pytest.fixture(scope="module")
def data(tiny_dataset):
    from proxycodec.formats.datasets import load_dataset

    return load_dataset(tiny_dataset)


def small_config(**kw):
    from proxycodec.train import FitConfig

    base = {"iters": 30, "max_width": None, "init_points": 250, "update_interval": 10, "predictor_warmup": 10,
            "predictor_hidden": 16, "predictor_blocks": 1, "checkpoint_every": 0, "log_every": 1e9, "seed": 3}
    base.update(kw)
    return FitConfig(**base)


def _fit(data, out, cfg, **kw):
    from proxycodec.train import fit

    return fit(data, out, cfg, dataset_root="tiny", log=lambda s: None, **kw)


def test_the_renderer_warms_up_off_the_clock_and_changes_nothing(data, tmp_path, monkeypatch):
    """Every trainer (``loop.run_until_done``) renders once before its clock starts, so a time budget buys training
    and not numba's first compilation; the warm-up changes no result."""
    import time

    from proxycodec import render

    state = torch.get_rng_state()
    assert render.warm_up("cpu") >= 0.0 and torch.equal(torch.get_rng_state(), state)  # no random stream drawn
    calls, real = [], render.warm_up

    def slow(backend="auto", device=None):  # as a first compilation would be
        calls.append(backend)
        time.sleep(5.0)
        return 5.0 + real(backend, device)

    monkeypatch.setattr(render, "warm_up", slow)
    logs = []
    from proxycodec.train import fit

    a = fit(data, tmp_path / "a.ply", small_config(iters=12), dataset_root="tiny", log=logs.append)
    assert calls == ["auto"] and sum("renderer ready in" in s for s in logs) == 1
    assert a.history[0]["it"] == 1 and a.history[0]["seconds"] < 5.0  # the clock after one step: no warm-up in it
    monkeypatch.setattr(render, "warm_up", lambda *args, **kw: 0.0)
    b = fit(data, tmp_path / "b.ply", small_config(iters=12), dataset_root="tiny", log=lambda s: None)
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    for k, v in a.model.decoder.state_dict().items():
        assert torch.equal(v, b.model.decoder.state_dict()[k]), k


def _assert_stored_as_fitted(fitted, decoded) -> None:
    """The container's offsets and scalings are the fitted scene's (matched by position; float32 rounding only)."""
    pos, dpos = fitted.positions.numpy(), decoded.positions.numpy()
    a, b = np.lexsort(pos.T[::-1]), np.lexsort(dpos.T[::-1])
    for name in ("offsets", "scalings"):
        x, y = getattr(fitted, name).numpy()[a], getattr(decoded, name).numpy()[b]
        assert np.abs(x - y).max() <= 1e-5 * (1 + np.abs(x).max()), name


def _fit_interrupted_and_resumed(data, out, cfg):
    """``cfg``'s fit interrupted at iteration 18 (a checkpoint), then resumed to the end: -> ``out``."""
    with pytest.raises(KeyboardInterrupt):
        _fit(data, out, cfg, stop_after=18)
    _fit(data, out, cfg, resume=True)
    return out


# ------------------------------------------------------------------------------------------------ metrics
class TestMetrics:
    def test_psnr_of_known_mse(self):
        a = np.zeros((8, 8, 3))
        assert psnr(a, a + 0.1) == pytest.approx(20.0)
        assert psnr(a, a + 0.01) == pytest.approx(40.0)
        assert mse_to_psnr(1e-3) == pytest.approx(30.0)
        assert psnr(a, a) == math.inf

    def test_ssim_identical_is_one(self):
        rng = np.random.default_rng(0)
        a = rng.random((20, 24, 3))
        assert ssim(a, a) == pytest.approx(1.0)
        t = torch.from_numpy(a).float()
        assert float(ssim_torch(t, t)) == pytest.approx(1.0, abs=1e-6)
        assert float(dssim(t, t)) == pytest.approx(0.0, abs=1e-6)

    def test_ssim_degrades_and_matches_skimage_order(self):
        rng = np.random.default_rng(1)
        a = rng.random((32, 32, 3))
        b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
        c = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
        assert 1 > ssim(a, b) > ssim(a, c) > 0
        ta, tb, tc = (torch.from_numpy(x).float() for x in (a, b, c))
        assert 1 > float(ssim_torch(ta, tb)) > float(ssim_torch(ta, tc))

    def test_ssim_tiny_images(self):
        a = np.zeros((5, 4, 3))
        assert ssim(a, a) == pytest.approx(1.0)  # 3x3 window
        assert ssim(np.zeros((2, 2, 3)), np.zeros((2, 2, 3))) is None

    def test_ssim_torch_gradient(self):
        a = torch.rand(16, 16, 3, requires_grad=True)
        b = torch.rand(16, 16, 3)
        dssim(a, b).backward()
        assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0


# ------------------------------------------------------------------------------------------------ config
class TestConfig:
    def test_rejects_bad_values(self):
        from proxycodec.train import FitConfig

        with pytest.raises(ProxycodecError):
            FitConfig(iters=None, time_budget=None)
        with pytest.raises(ProxycodecError):
            FitConfig(embedding="bogus")
        with pytest.raises(ProxycodecError):
            FitConfig(xi_min=0.5, xi_max=0.2)
        with pytest.raises(ProxycodecError, match="proxy selection"):
            FitConfig(proxy_selection="fps")
        with pytest.raises(ProxycodecError, match="rate term"):
            FitConfig(quant_cells=8, lambda_rate=0.0)
        with pytest.raises(ProxycodecError, match="quantisation cells"):
            FitConfig(quant_cells=33)
        assert FitConfig(quant_cells=8).quant_cells == 8
        for bad in (0.0, -1e-3, float("nan")):
            with pytest.raises(ProxycodecError, match="learning rates must be positive"):
                FitConfig(lr_quant_step=bad)

    def test_anchor_growing_ends_where_stage_2_starts_unless_told_otherwise(self):
        from proxycodec.train import FitConfig

        assert FitConfig().update_until == FitConfig().stage2_start == 0.5
        assert FitConfig(stage2_start=0.3).update_until == 0.3
        assert FitConfig(stage2_start=0.3, update_until=0.2).update_until == 0.2
        c = FitConfig(stage2_start=0.4)
        assert c.to_json()["update_until"] == 0.4 and FitConfig.from_json(c.to_json()) == c

    def test_encode_config_validates_when_built(self):
        from proxycodec.codec import EncodeConfig

        for bad in ({"proxy_ratio": 0.0}, {"feature_bits": 17}, {"weights_dtype": "bf16"}, {"zstd_level": 0},
                    {"leaf_sample": 1.5}, {"proxy_selection": "fps"}, {"cell_size": -1.0}):
            with pytest.raises(ProxycodecError):
                EncodeConfig(**bad)
        assert EncodeConfig(feature_bits=32).feature_bits == 32

    def test_json_round_trip(self):
        from proxycodec.train import FitConfig

        c = FitConfig(iters=7, gate=False, lambda_recon=(0.2, 0.02))
        assert FitConfig.from_json(json.loads(json.dumps(c.to_json()))) == c


# ------------------------------------------------------------------------------------------------ training
class TestFit:
    def test_loss_decreases_and_psnr_increases(self, data):
        from proxycodec.metrics import psnr as psnr_
        from proxycodec.model import render_scene
        from proxycodec.train import Trainer

        torch.set_num_threads(2)
        tr = Trainer(data, small_config(iters=40, proxies=False), "tiny")
        i = data.train_indices[0]
        gt = data.load_image(i, 1.0)

        def view_psnr():
            with torch.no_grad():
                r = render_scene(tr.anchors.scene(), tr.decoder, data.cameras[i], 1.0, background=tr.bg)
            return psnr_(r.image.clamp(0, 1), gt)

        p0 = view_psnr()
        losses = [tr.train_step()["loss"] for _ in range(40)]
        p1 = view_psnr()
        assert all(math.isfinite(x) for x in losses)
        assert np.mean(losses[-8:]) < 0.8 * np.mean(losses[:8])
        assert p1 > p0 + 1.0

    def test_deterministic_for_a_seed(self, data):
        from proxycodec.train import Trainer

        runs = []
        for _ in range(2):
            tr = Trainer(data, small_config(iters=20), "tiny")
            runs.append([tr.train_step()["loss"] for _ in range(6)])
        assert runs[0] == runs[1]

    def test_output_reloads_in_a_new_process(self, data, tmp_path):
        from proxycodec.model import SceneModel, weights_path_for
        from proxycodec.proxy import load_fitted_predictor as load_predictor
        from proxycodec.train import checkpoint_path_for

        out = tmp_path / "scene.ply"
        res = _fit(data, out, small_config(iters=24))
        assert out.exists() and weights_path_for(out).exists()
        assert not checkpoint_path_for(out).exists()  # removed after success
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left
        assert res.iterations == 24
        # Stage 2 ran: the sidecar holds the predictor and the proxy mask, and leaf features ARE its predictions.
        pred, mask = load_predictor(weights_path_for(out))
        assert pred is not None and mask.dtype == bool and 0 < mask.sum() < len(mask)
        m = SceneModel.load(out)
        assert m.scene.num_anchors == len(mask)
        from proxycodec.proxy import predictor_neighbours

        near = torch.from_numpy(predictor_neighbours(m.scene.positions, mask, pred.config))
        leaves = torch.from_numpy(~mask).nonzero().squeeze(1)
        with torch.no_grad():
            f, _ = pred.predict(m.scene.positions, m.scene.features, near, leaves)
        assert torch.allclose(f, m.scene.features[leaves], atol=1e-5)
        # Stored cameras: the test views first.
        assert len(m.cameras) == len(data.cameras)
        assert m.cameras[0].name == data.cameras[data.test_indices[0]].name
        expected = m.render(m.cameras[0], 0.5).image.numpy()
        np.save(tmp_path / "expected.npy", expected)
        code = ("import numpy as np, sys; from proxycodec.model import SceneModel; "
                f"m = SceneModel.load({str(out)!r}); img = m.render(m.cameras[0], 0.5).image.numpy(); "
                f"e = np.load({str(tmp_path / 'expected.npy')!r}); "
                "sys.exit(0 if np.isfinite(img).all() and np.allclose(img, e, atol=1e-5) else 1)")
        assert subprocess.run([sys.executable, "-c", code], timeout=120, check=False).returncode == 0

    def test_resume_continues_at_the_right_iteration(self, data, tmp_path):
        from proxycodec.model import SceneModel
        from proxycodec.train import checkpoint_path_for

        cfg = small_config(iters=24)
        _fit(data, tmp_path / "ref.ply", cfg)
        out = tmp_path / "scene.ply"
        with pytest.raises(KeyboardInterrupt):
            _fit(data, out, cfg, stop_after=14)  # interrupted in stage 2 (it starts at 12)
        assert checkpoint_path_for(out).exists()
        assert not out.exists()
        logs = []
        from proxycodec.train import fit

        res = fit(data, out, cfg, dataset_root="tiny", resume=True, log=logs.append)
        assert any("resumed" in s and "iteration 14" in s for s in logs)
        assert res.iterations == 24
        a, b = SceneModel.load(out).scene, SceneModel.load(tmp_path / "ref.ply").scene
        assert a.num_anchors == b.num_anchors
        for name in ("positions", "features", "offsets", "scalings"):  # bit for bit: every state is checkpointed
            assert torch.equal(getattr(a, name), getattr(b, name)), name

    def test_resume_refuses_other_settings_and_missing_checkpoint(self, data, tmp_path):
        out = tmp_path / "scene.ply"
        with pytest.raises(ProxycodecError, match="no checkpoint"):
            _fit(data, out, small_config(), resume=True)
        with pytest.raises(KeyboardInterrupt):
            _fit(data, out, small_config(), stop_after=3)
        with pytest.raises(ProxycodecError, match="different settings"):
            _fit(data, out, small_config(embedding="none"), resume=True)

    def test_no_partial_output_after_an_exception(self, data, tmp_path, monkeypatch):
        from proxycodec import train
        from proxycodec.model import SceneModel

        out = tmp_path / "scene.ply"

        def boom(*a, **k):
            raise RuntimeError("disk full")

        # An exception while saving the pair leaves neither file (nor temporaries) behind.
        real = SceneModel.save

        def half(model, *args, **kwargs):
            real(model, *args, **kwargs)
            boom()

        monkeypatch.setattr(SceneModel, "save", half)
        with pytest.raises(RuntimeError):
            _fit(data, out, small_config(iters=4, proxies=False))
        assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ckpt.pxc"]
        # An exception during training: no output either.
        monkeypatch.setattr(train.Trainer, "train_step", boom)
        with pytest.raises(RuntimeError):
            _fit(data, tmp_path / "other.ply", small_config(iters=4))
        assert not (tmp_path / "other.ply").exists()
        assert not (tmp_path / "other.weights.pxc").exists()

    def test_predicted_offsets_are_what_is_stored_and_encode_follows(self, data, tmp_path):
        """fit --predict-offsets: the leaves' offsets in the PLY are the predictor's (what stage 2 rendered), a
        resumed run ends where an uninterrupted one does, and encode stores proxy offsets only."""
        from proxycodec.codec import EncodeConfig, decode, encode
        from proxycodec.model import SceneModel, weights_path_for
        from proxycodec.proxy import load_fitted_predictor as load_predictor
        from proxycodec.proxy import predictor_neighbours

        cfg = small_config(iters=24, predict_offsets=True)
        out = tmp_path / "po.ply"
        _fit(data, out, cfg)
        pred, mask = load_predictor(weights_path_for(out))
        assert pred.config.predict_offsets
        m = SceneModel.load(out)
        s = m.scene
        near = torch.from_numpy(predictor_neighbours(s.positions, mask, pred.config))
        leaves = torch.from_numpy(~mask).nonzero().squeeze(1)
        with torch.no_grad():
            f, o = pred.predict(s.positions, s.features, near, leaves, s.offsets)
        assert torch.allclose(f, s.features[leaves], atol=1e-5)
        assert torch.allclose(o, s.offsets[leaves], atol=1e-5)
        # interrupted in stage 2 and resumed: the same scene
        out2 = tmp_path / "po2.ply"
        with pytest.raises(KeyboardInterrupt):
            _fit(data, out2, cfg, stop_after=16)
        _fit(data, out2, cfg, resume=True)
        assert torch.allclose(SceneModel.load(out2).scene.offsets, s.offsets, atol=1e-4)
        # encode follows the fitted predictor: proxy offsets only; asking to store them is refused
        rep = encode(out, tmp_path / "po.pxc", EncodeConfig(max_cameras=1))
        assert rep.meta["offsets"] == "predicted" and rep.proxies == int(mask.sum())
        names = {sec["name"] for sec in rep.sections}
        assert "proxy/offsets" in names and "anchors/offsets" not in names
        a = m.render(m.cameras[0], 0.5).image
        b = decode(rep.path).render(m.cameras[0], 0.5).image
        assert mse_to_psnr(float(((a - b) ** 2).mean())) > 35.0  # 8-bit quantisation only
        with pytest.raises(ProxycodecError, match="predicts"):
            encode(out, tmp_path / "po_store.pxc", EncodeConfig(predict_offsets=False))
        with pytest.raises(ProxycodecError, match="residual"):
            small_config(predict_offsets=True, predictor="proxy-leaf-mlp")

    def test_rate_term_renders_on_learned_grids_that_encode_keeps(self, data, tmp_path):
        """fit --lambda-rate: the PLY's attributes lie on the learned grids (what stage 2 rendered), encode stores
        exactly them (offsets and scalings bit-close, 8-bit steps not imposed), and a run resumed in stage 2 (rate
        model in the checkpoint) ends where an uninterrupted one does."""
        from proxycodec.codec import decode, encode
        from proxycodec.model import SceneModel

        cfg = small_config(iters=24, lambda_rate=1e-3)
        out = tmp_path / "r.ply"
        _fit(data, out, cfg)
        m = SceneModel.load(out)
        grids = m.scene.metadata["quant_steps"]
        off = m.scene.offsets.numpy().reshape(len(m.scene.offsets), -1)
        k = (off - np.asarray(grids["offsets"]["origin"])) / np.asarray(grids["offsets"]["step"])
        assert np.abs(k - np.rint(k)).max() < 1e-3
        rep = encode(out, tmp_path / "r.pxc", max_cameras=1, entropy="model", entropy_iters=50)
        assert rep.meta["quant"]["offsets"]["scale"] == pytest.approx(grids["offsets"]["step"])
        _assert_stored_as_fitted(m.scene, decode(rep.path).scene)
        m2 = SceneModel.load(_fit_interrupted_and_resumed(data, tmp_path / "r2.ply", cfg))
        assert m2.scene.metadata["quant_steps"]["offsets"]["step"] == pytest.approx(grids["offsets"]["step"],
                                                                                    rel=1e-3)
        assert torch.allclose(m2.scene.offsets, m.scene.offsets, atol=1e-3)

    def test_the_grids_coarsen_at_the_pace_lr_quant_step_sets(self, data, tmp_path):
        """fit --lr-quant-step: two runs alike but for the grids' learning rate (the same up to the stage switch, so
        on the same starting grids) end on coarser grids with the faster one: the rate's pull, not a fixed depth,
        sets them, at the pace the option gives. Adam moves a log-step by about ``lr`` per step (at most ~3.2 lr
        with betas 0.9 / 0.999), so the two differ by no more than that allows in the stage-2 iterations."""
        from proxycodec.model import SceneModel

        slow, fast = 2e-4, 5e-2
        log_steps = {}
        for lr in (slow, fast):
            cfg = small_config(iters=24, lambda_rate=1e-3, lr_quant_step=lr)
            _fit(data, tmp_path / f"g{lr}.ply", cfg)
            grids = SceneModel.load(tmp_path / f"g{lr}.ply").scene.metadata["quant_steps"]
            log_steps[lr] = np.concatenate([np.log(g["step"]) for g in grids.values()])
        moved = log_steps[fast] - log_steps[slow]
        assert moved.mean() > 0.1 and (moved > 0).mean() > 0.8, moved
        iters2 = 24 - int(24 * small_config().stage2_start)
        assert np.abs(moved).max() <= 3.2 * (fast + slow) * iters2, moved

    def test_per_cell_levels_render_on_the_grids_the_container_decodes(self, data, tmp_path):
        """fit --quant-cells: each anchor's values lie on its cell's grid (channel step x 2^(level / 4)), the levels
        move (a high level learning rate here), and the container (scene format 5, zstd and entropy-coded) decodes
        to the PLY's attributes; a resumed run ends where an uninterrupted one does."""
        from proxycodec.codec import decode, encode, stats
        from proxycodec.model import SceneModel, weights_path_for
        from proxycodec.proxy import load_fitted_predictor
        from proxycodec.sections import anchor_levels, level_multipliers, position_cells

        cfg = small_config(iters=24, lambda_rate=1e-3, quant_cells=3, lr_quant_level=0.5)
        out = tmp_path / "c.ply"
        _fit(data, out, cfg)
        m = SceneModel.load(out)
        grids = m.scene.metadata["quant_steps"]
        pos, voxel = m.scene.positions.numpy(), float(m.scene.voxel_size)
        leaf = ~load_fitted_predictor(weights_path_for(out))[1]
        tables = {k: np.asarray(g["levels"]["table"]) for k, g in grids.items()}
        assert all(g["levels"]["cells"] == 3 for g in grids.values())
        assert all(np.any(t != 0) for t in tables.values()), tables
        off = m.scene.offsets.numpy().reshape(len(pos), -1)
        lv = anchor_levels(grids["offsets"]["levels"], pos, voxel, leaf, ValueError)
        assert len(np.unique(lv)) > 1
        step = np.asarray(grids["offsets"]["step"])[None] * level_multipliers()[lv + 8][:, None]
        k = (off - np.asarray(grids["offsets"]["origin"])) / step
        assert np.abs(k - np.rint(k)).max() < 1e-3
        k1 = (off - np.asarray(grids["offsets"]["origin"])) / np.asarray(grids["offsets"]["step"])
        assert np.abs(k1 - np.rint(k1)).max() > 0.1  # not on the per-channel grid alone
        for entropy in ("zstd", "model"):
            rep = encode(out, tmp_path / f"c_{entropy}.pxc", max_cameras=1, entropy=entropy, entropy_iters=50,
                         positions="delta")
            assert rep.meta["scene_format"] == 5 and rep.meta["quant"]["offsets"]["levels"]["cells"] == 3
            assert ("entropy" in rep.meta) == (entropy == "model")
            cells = position_cells(pos, voxel, 3)  # offsets: every anchor's, one entry per occupied cell and kind
            occupied = len(np.unique(cells[leaf])) + len(np.unique(cells[~leaf]))
            assert stats(rep.path)["quant_levels"]["offsets"] == {"cells": 3, "entries": occupied}
            assert occupied >= len(np.unique(cells))
            _assert_stored_as_fitted(m.scene, decode(rep.path).scene)
        m2 = SceneModel.load(_fit_interrupted_and_resumed(data, tmp_path / "c2.ply", cfg))
        assert m2.scene.metadata["quant_steps"]["offsets"]["levels"] == grids["offsets"]["levels"]

    def test_l_recon_at_weight_zero_is_skipped_without_changing_the_run(self, data, monkeypatch):
        """lambda_recon 0 (the default) skips L_recon's predictor pass; the run is bit for bit the one that
        computes it and adds 0 times it (the leaf sample is still drawn)."""
        from proxycodec.train import Trainer

        calls = []
        orig = Trainer.leaf_tables

        def run(force):
            def spy(self, vis, with_recon=True, rounded=None):
                calls.append(with_recon)
                return orig(self, vis, True if force else with_recon, rounded)

            monkeypatch.setattr(Trainer, "leaf_tables", spy)
            tr = Trainer(data, small_config(iters=20), "tiny")
            losses = [tr.train_step()["loss"] for _ in range(20)]
            assert tr.stage == 2
            return losses, tr.anchors.features.detach().clone(), [p.detach().clone()
                                                                  for p in tr.predictor.parameters()]

        a, b = run(False), run(True)
        assert calls and not any(calls)  # the default never asked for L_recon
        assert a[0] == b[0] and torch.equal(a[1], b[1])
        assert all(torch.equal(x, y) for x, y in zip(a[2], b[2]))

    def test_spread_proxy_selection_is_the_stored_split(self, data, tmp_path):
        from proxycodec.model import SceneModel, weights_path_for
        from proxycodec.proxy import select_proxies
        from proxycodec.proxy import load_fitted_predictor as load_predictor

        out = tmp_path / "spread.ply"
        _fit(data, out, small_config(iters=12, proxy_selection="spread", proxy_cell=0.3))
        _, mask = load_predictor(weights_path_for(out))
        pos = SceneModel.load(out).scene.positions
        assert np.array_equal(mask, select_proxies(pos, 0.3, 0.3, 0, "spread"))
        assert not np.array_equal(mask, select_proxies(pos, 0.3, 0.3, 0, "random"))

    def test_ablation_switches(self, data, tmp_path):
        from proxycodec.model import SceneModel
        from proxycodec.proxy import load_fitted_predictor as load_predictor

        out = tmp_path / "plain.ply"
        _fit(data, out, small_config(iters=6, fixed_res=True, gate=False, embedding="none", proxies=False))
        m = SceneModel.load(out)
        assert m.decoder.config.embedding == "none" and not m.decoder.config.gate.enabled
        assert load_predictor(out.with_name("plain.weights.pxc")) == (None, None)

    def test_resolution_sampling_laws(self):
        from proxycodec.loop import draw_xi
        from proxycodec.train import FitConfig

        u = (np.arange(20000) + 0.5) / 20000
        xs = {s: np.array([draw_xi((0.1, 1.0), s, v) for v in u]) for s in ("uniform", "pixels", "log")}
        assert xs["uniform"].mean() == pytest.approx(0.55, abs=1e-4)
        assert (xs["pixels"] ** 2).mean() == pytest.approx((0.01 + 1.0) / 2, abs=1e-4)  # uniform in pixel count
        assert np.median(xs["log"]) == pytest.approx(math.sqrt(0.1), abs=1e-3)  # uniform in log xi
        assert all(x.min() >= 0.1 and x.max() <= 1.0 for x in xs.values())
        assert draw_xi((0.1, 1.0), "uniform", 0.37) == 0.1 + 0.9 * 0.37  # the paper's formula, bit for bit
        with pytest.raises(ProxycodecError, match="resolution sampling"):
            FitConfig(xi_sampling="cosine")
        with pytest.raises(ProxycodecError, match="xi_full_share"):
            FitConfig(xi_full_share=1.5)

    def test_full_share_and_high_res_statistics(self, data):
        from proxycodec.train import Trainer

        def run(**kw):
            tr = Trainer(data, small_config(iters=200, proxies=False, **kw), "tiny")
            calls = []
            observe = tr.strategy.observe
            tr.strategy.observe = lambda r, w, h: (calls.append(w), observe(r, w, h))
            xis = [tr.train_step()["xi"] for _ in range(60)]
            return np.array(xis), calls

        base, _ = run(xi_full_share=0.0)
        share, _ = run(xi_full_share=0.5)
        assert (base == 1.0).mean() == 0.0 and 0.3 < (share == 1.0).mean() < 0.7
        assert share[share < 1.0].min() >= 0.1
        _, all_calls = run()
        hi, hi_calls = run(stats_min_xi=0.6)
        assert min(hi_calls) >= round(0.6 * SIZE) and len(hi_calls) < len(all_calls)

    def test_growing_and_pruning(self, data):
        from proxycodec.train import Trainer

        tr = Trainer(data, small_config(iters=100, proxies=False, grad_threshold=1e-6), "tiny")
        n0 = tr.anchors.num_anchors
        for _ in range(40):
            tr.train_step()
        assert tr.anchors.num_anchors != n0
        K = tr.anchors.n_offsets
        assert tr.strategy.offset_denom.shape[0] == tr.anchors.num_anchors * K
        assert tr.opt.m["features"].shape == tr.anchors.features.shape

    def test_growing_stops_at_the_anchor_cap_and_has_none_by_default(self, data):
        from proxycodec.errors import ProxycodecError
        from proxycodec.train import FitConfig, Trainer

        assert FitConfig().max_anchors is None  # the scene decides (Scaffold-GS has no cap)
        free = Trainer(data, small_config(iters=100, proxies=False, grad_threshold=1e-6), "tiny")
        n0 = free.anchors.num_anchors
        for _ in range(40):
            free.train_step()
        grown = free.anchors.num_anchors - n0
        assert grown > 10
        capped = Trainer(data, small_config(iters=100, proxies=False, grad_threshold=1e-6, min_opacity=0.0,
                                            max_anchors=n0 + 3), "tiny")
        for _ in range(40):
            capped.train_step()
        assert n0 < capped.anchors.num_anchors <= n0 + 3
        with pytest.raises(ProxycodecError, match="anchor cap"):
            FitConfig(max_anchors=0)

    def test_a_target_size_caps_the_anchors_and_coarsens_the_starting_voxel(self):
        """``fit --target-size``: the bytes become an anchor cap by the measured model (the smaller of it and
        ``max_anchors``), the voxel coarsens to the finest 2^(k/8) step that starts under 80% of the cap, a given
        voxel size is kept (and subsampled as ``max_anchors`` does), and a budget too small for one anchor is a one-line
        error. The setting survives the configuration's JSON."""
        from types import SimpleNamespace

        from proxycodec.errors import ProxycodecError
        from proxycodec.train import (
            FIT_ANCHOR_BYTES, FIT_BASE_BYTES, FitConfig, anchors_for_bytes, budget_voxel, initial_anchors, voxelise,
        )

        cap = anchors_for_bytes(200_000, FIT_BASE_BYTES, FIT_ANCHOR_BYTES)
        assert cap == int((200_000 - FIT_BASE_BYTES) / FIT_ANCHOR_BYTES) > 0
        assert FitConfig(target_size=200_000).max_anchors == cap
        assert FitConfig(target_size=200_000, max_anchors=cap - 5).max_anchors == cap - 5
        assert FitConfig(target_size=200_000, max_anchors=cap + 5).max_anchors == cap
        cfg = FitConfig(target_size=200_000, voxel_rule="spacing")
        assert FitConfig.from_json(cfg.to_json()) == cfg
        with pytest.raises(ProxycodecError, match="holds no anchor") as e:
            FitConfig(target_size=FIT_BASE_BYTES)
        assert "\n" not in str(e.value)
        rng = np.random.default_rng(0)
        pts = rng.uniform(0, 1, (4000, 3))
        for budget in (1, 37, 500, 10**6):
            v = budget_voxel(pts, 0.01, budget)
            assert len(voxelise(pts, v)) <= budget
            assert v == 0.01 or len(voxelise(pts, v / 2 ** (1 / 8))) > budget  # the finest step that fits
        # a target whose cap is 100 anchors: 80 at most to start (the rest is growth's), on a coarser voxel
        target = int(FIT_BASE_BYTES + 100.5 * FIT_ANCHOR_BYTES)
        sfm = SimpleNamespace(points=pts, point_colors=None, bounds=np.array([[0.0] * 3, [1.0] * 3]))
        free = initial_anchors(sfm, FitConfig(voxel_rule="extent"), np.random.default_rng(0))
        ia = initial_anchors(sfm, FitConfig(voxel_rule="extent", target_size=target), np.random.default_rng(0))
        assert len(free.positions) > 100 and 0 < len(ia.positions) <= 80 and ia.voxel > free.voxel
        assert len(voxelise(pts, ia.voxel / 2 ** (1 / 8))) > 80
        given = initial_anchors(sfm, FitConfig(voxel_size=free.voxel, target_size=target), np.random.default_rng(0))
        assert given.voxel == free.voxel and len(given.positions) == 100

    def test_initial_voxel_rules(self):
        from types import SimpleNamespace

        from proxycodec.errors import ProxycodecError
        from proxycodec.loop import knn_scale
        from proxycodec.train import FitConfig, initial_anchors

        # SfM points on a 0.05 lattice (6 x 5 x 4 cells), each seen twice with a small jitter, and one far point
        g = np.stack(np.meshgrid(np.arange(6), np.arange(5), np.arange(4), indexing="ij"), -1).reshape(-1, 3) * 0.05
        rng = np.random.default_rng(0)
        pts = np.concatenate([g, g + rng.uniform(-0.002, 0.002, g.shape), [[2.0, 2.0, 2.0]]])
        bounds = np.array([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]])
        sfm = SimpleNamespace(points=pts, point_colors=None, bounds=bounds)
        assert FitConfig().voxel_rule == "auto"  # the scene and the run's length decide (SPEC.md section 5)
        # auto by the run's length in iterations: spacing from density_iters on, extent below
        voxel = initial_anchors(sfm, FitConfig(iters=1000), np.random.default_rng(0)).voxel
        assert 0 < voxel < 0.0035 * 2
        voxel = initial_anchors(sfm, FitConfig(iters=999), np.random.default_rng(0)).voxel
        assert voxel == pytest.approx(2.0 / 128)
        voxel = initial_anchors(sfm, FitConfig(iters=999, density_iters=999), np.random.default_rng(0)).voxel
        assert 0 < voxel < 0.0035 * 2
        with pytest.raises(ProxycodecError, match="density switch"):
            FitConfig(density_iters=0)
        ia = initial_anchors(sfm, FitConfig(voxel_rule="extent"), np.random.default_rng(0))
        a, voxel = ia.positions, ia.voxel
        assert voxel == pytest.approx(2.0 / 128) and len(a) == len(np.unique(np.round(pts / voxel), axis=0))
        ia = initial_anchors(sfm, FitConfig(voxel_rule="spacing"), np.random.default_rng(0))
        a, voxel = ia.positions, ia.voxel
        # the median nearest-neighbour distance is the jitter (each lattice point has its twin): below the lattice step
        assert 0 < voxel < 0.0035 * 2 and len(a) > len(g)
        sparse = SimpleNamespace(points=np.concatenate([g, [[2.0, 2.0, 2.0]]]), point_colors=None, bounds=bounds)
        ia = initial_anchors(sparse, FitConfig(voxel_rule="spacing"), np.random.default_rng(0))
        a, voxel = ia.positions, ia.voxel
        assert voxel == pytest.approx(0.05) and len(a) == len(g) + 1  # one anchor per point: the scene decides
        # a cap subsamples the initial set (seeded); a given size wins over the rule
        capped = FitConfig(voxel_rule="spacing", max_anchors=50)
        a1 = initial_anchors(sparse, capped, np.random.default_rng(1)).positions
        a2 = initial_anchors(sparse, capped, np.random.default_rng(1)).positions
        assert len(a1) == 50 and np.array_equal(a1, a2)
        voxel = initial_anchors(sparse, FitConfig(voxel_rule="spacing", voxel_size=0.3), np.random.default_rng(0)
                                ).voxel
        assert voxel == 0.3
        # the Gaussians start as large as at the spacing density: the lattice's 0.05 against the 0.2 voxel's 8
        # cube corners 0.2 apart (and the far point); Scaffold-GS's 1 at spacing, without SfM points, or as given
        ia = initial_anchors(sparse, FitConfig(voxel_size=0.2), np.random.default_rng(0))
        assert len(ia.positions) == 9 and ia.gaussian_scale == pytest.approx(0.25)
        sc = ia.scalings()
        np.testing.assert_allclose(sc[:, :3], np.log(knn_scale(ia.positions))[:, None].repeat(3, 1))
        np.testing.assert_allclose(sc[:, 3:] - sc[:, :3], np.log(0.25))
        assert initial_anchors(sparse, FitConfig(voxel_size=0.2, init_gaussian_scale=0.7), np.random.default_rng(0)
                               ).gaussian_scale == 0.7
        assert initial_anchors(sparse, FitConfig(voxel_rule="spacing"), np.random.default_rng(0)).gaussian_scale == 1
        with pytest.raises(ProxycodecError, match="initial Gaussian scale"):
            FitConfig(init_gaussian_scale=0.0)
        # no SfM points (Blender): random points in the bounds, where spacing means nothing: the extent rule
        blender = SimpleNamespace(points=None, point_colors=None, bounds=bounds)
        voxel = initial_anchors(blender, FitConfig(voxel_rule="spacing", init_points=300), np.random.default_rng(0)
                                ).voxel
        assert voxel == pytest.approx(2.0 / 128)
        ia = initial_anchors(blender, FitConfig(voxel_size=0.5, init_points=300), np.random.default_rng(0))
        assert ia.gaussian_scale == 1 and ia.colors is None
        with pytest.raises(ProxycodecError, match="voxel rule"):
            FitConfig(voxel_rule="median")


    def test_cell_means_average_each_anchors_points(self):
        from proxycodec.train import cell_means, voxelise

        pts = np.array([[0.0, 0, 0], [0.04, 0, 0], [1.0, 0, 0], [0.0, 2.0, 0], [1.02, 0, 0]])
        cols = np.array([[255, 0, 0], [0, 0, 255], [10, 20, 30], [0, 255, 0], [30, 40, 50]], dtype=np.float64)
        anchors = voxelise(pts, 0.1)
        got = cell_means(pts, cols, 0.1, anchors)
        want = {(0, 0, 0): [127.5, 0, 127.5], (10, 0, 0): [20, 30, 40], (0, 20, 0): [0, 255, 0]}
        for a, c in zip(anchors, got):
            np.testing.assert_allclose(c, want[tuple(np.round(a / 0.1).astype(int))])
        # a subsampled set (``max_anchors``), in float32 as the trainer holds it; one value per point
        sub = anchors[[2, 0]].astype(np.float32).astype(np.float64)
        np.testing.assert_allclose(cell_means(pts, cols, 0.1, sub), got[[2, 0]])
        np.testing.assert_allclose(cell_means(pts, cols[:, 0], 0.1, sub), got[[2, 0], 0])

    def test_color_init_fits_the_colours_and_keeps_the_other_heads(self):
        from proxycodec.decoder import DecoderConfig, GaussianDecoder
        from proxycodec.train import fit_initial_colors

        torch.manual_seed(0)
        dec = GaussianDecoder(DecoderConfig(scene_center=(0.0, 0.0, 0.0), scene_radius=2.0))
        g = torch.Generator().manual_seed(1)
        pos = torch.rand(64, 3, generator=g) * 2 - 1
        target = torch.rand(64, 3, generator=g) * 0.8 + 0.1
        cams = torch.tensor([[4.0, 0, 0], [0, 4.0, 0], [0, 0, 4.0], [-3.0, 2, 1]])
        feats = torch.zeros(64, dec.config.feat_dim)
        x0 = dec.mlp_input(pos, feats, cams[0], 1.0)[1]
        op0, cov0 = torch.tanh(dec.mlp_opacity(x0)), dec.mlp_cov(x0)
        before, after = fit_initial_colors(dec, pos, feats, target, cams, 150, 0.01, torch.Generator().manual_seed(0))
        assert before > 0.15 and after < 0.03 and feats.abs().sum() > 0  # the features were written in place
        with torch.no_grad():  # the decoder's own forward, from a camera it trained with and from a new one
            for cam in (cams[3], torch.tensor([0.0, -4.0, 1.0])):
                ng = dec(pos, feats, torch.zeros(64, 10, 3), torch.zeros(64, 6), cam, 1.0)
                assert (ng.colors - target[ng.anchor_index]).abs().mean() < 0.05
            x = dec.mlp_input(pos, feats, cams[0], 1.0)[1]
            assert (torch.tanh(dec.mlp_opacity(x)) - op0).abs().mean() < 0.05
            assert (dec.mlp_cov(x) - cov0).abs().mean() < 0.05

    def test_fit_starts_from_the_sfm_colours(self, data, tmp_path):
        """With SfM point colours, ``fit`` first fits the anchors' colours to them (on the clock; ``color_init_steps``
        0 or no colours: zero features, as Scaffold-GS), and a resumed run, which does not repeat it, ends where an
        uninterrupted one does."""
        from dataclasses import replace

        from proxycodec.train import Trainer, fit

        lo, hi = data.bounds
        rng = np.random.default_rng(0)
        pts = (lo + (hi - lo) * rng.uniform(0.2, 0.8, (300, 3))).astype(np.float32)
        cols = np.tile(np.array([[200, 40, 90]], np.uint8), (300, 1))
        sfm = replace(data, points=pts, point_colors=cols)
        logs = []
        cfg = small_config(iters=1, voxel_rule="extent")
        res = fit(sfm, tmp_path / "a.ply", cfg, dataset_root="tiny", log=logs.append)
        line = next(s for s in logs if s.startswith("colour init"))
        assert float(line.split("->")[1].split()[0]) < 0.05
        assert res.history[0]["seconds"] > float(line.split(",")[-1].split()[0]) - 0.05  # on the clock
        tr = Trainer(sfm, cfg, "tiny")
        tr.color_init()
        cam = sfm.cameras[sfm.train_indices[0]]
        ng = tr.decoder(tr.anchors.positions, tr.anchors.features, tr.anchors.offsets, tr.anchors.scalings,
                        torch.as_tensor(cam.center, dtype=torch.float32), 1.0)
        assert ng.count and (ng.colors - torch.tensor([200, 40, 90]) / 255.0).abs().max() < 0.1
        for off in (Trainer(sfm, replace(cfg, color_init_steps=0), "tiny"), Trainer(data, cfg, "tiny")):
            off.color_init()
            assert off.elapsed == 0 and not off.anchors.features.detach().any()
        # determinism and resume
        cfg = small_config(iters=24, voxel_rule="extent")
        with pytest.raises(KeyboardInterrupt):
            fit(sfm, tmp_path / "r.ply", cfg, dataset_root="tiny", log=lambda s: None, stop_after=14)
        fit(sfm, tmp_path / "r.ply", cfg, dataset_root="tiny", log=lambda s: None, resume=True)
        fit(sfm, tmp_path / "u.ply", cfg, dataset_root="tiny", log=lambda s: None)
        assert (tmp_path / "r.ply").read_bytes() == (tmp_path / "u.ply").read_bytes()


# ------------------------------------------------------------------------------------------------ CLI
def test_auto_density_follows_the_run_length(data, tmp_path):
    """``voxel_rule="auto"`` on a dataset with SfM points: a length in iterations decides by itself; under a time
    budget the pace of the probe steps at the spacing density decides, a switch to extent keeps the probe's seconds
    spent, the choice is recorded, and a run resumed with "auto" continues at the density it chose."""
    from dataclasses import replace

    from proxycodec.model import SceneModel
    from proxycodec.train import DENSITY_PROBE_STEPS, FIT_ANCHOR_BYTES, FIT_BASE_BYTES, fit

    lo, hi = data.bounds
    extent = float(np.max(hi - lo))
    step = extent / 16  # the SfM points' spacing: the spacing voxel, 8x the extent / 128 one
    grid = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), -1).reshape(-1, 3) * step
    sfm = replace(data, points=((lo + hi) / 2 + grid - 1.5 * step).astype(np.float32))
    spacing, coarse = pytest.approx(step, rel=1e-5), pytest.approx(extent / 128, rel=1e-5)

    def run(name, **kw):
        logs = []
        res = fit(sfm, tmp_path / name, small_config(**kw), dataset_root="tiny", log=logs.append)
        return res, res.extra_meta["fit"]["density"], logs

    res, dens, logs = run("a.ply", iters=12)  # 12 < 1000 iterations: extent, no probe
    assert res.model.scene.voxel_size == coarse and dens["chose"] == "extent" and "probe_steps" not in dens
    assert any("density auto: extent" in s for s in logs)
    res, dens, _ = run("b.ply", iters=12, density_iters=12)
    assert res.model.scene.voxel_size == spacing and dens["chose"] == "spacing"
    budget = 1.5 + 2 * res.seconds  # time for the probe's 10 steps and more, on a machine however busy
    # under a time budget: probe steps at the spacing density, then the rule; every pace is below 10^9 iterations
    res, dens, logs = run("c.ply", iters=None, time_budget=budget, density_iters=10 ** 9)
    assert res.model.scene.voxel_size == coarse and dens["chose"] == "extent"
    assert dens["probe_steps"] == DENSITY_PROBE_STEPS and 0 < dens["probe_seconds"] <= res.seconds + 5e-4  # ms
    assert res.history[0]["seconds"] >= dens["probe_seconds"]  # the extent run's clock starts where the probe's ends
    assert any("steps at the spacing density" in s and s.endswith(": extent") for s in logs)
    res, dens, _ = run("d.ply", iters=None, time_budget=budget, density_iters=1)  # the probe's run goes on
    assert res.model.scene.voxel_size == spacing and dens["chose"] == "spacing"
    assert res.history[0]["it"] == 1 and res.iterations > DENSITY_PROBE_STEPS
    assert SceneModel.load(tmp_path / "d.ply").scene.voxel_size == spacing
    # with a target size whose cap (10 anchors) the spacing voxel's 64 exceed: the probe runs on the coarser voxel
    # the budget gives, and says so
    target = int(FIT_BASE_BYTES + 10.5 * FIT_ANCHOR_BYTES)
    res, dens, logs = run("t.ply", iters=None, time_budget=budget, density_iters=1, target_size=target)
    v = res.model.scene.voxel_size
    assert v > 1.05 * step and dens["chose"] == "spacing"
    line = next(s for s in logs if "steps at the spacing density" in s)
    assert f"voxel {v:.4g}, within the target size" in line
    # resumed with "auto": the checkpoint's choice stands, and the run ends where an uninterrupted one does
    cfg = small_config(iters=24)
    with pytest.raises(KeyboardInterrupt):
        fit(sfm, tmp_path / "r.ply", cfg, dataset_root="tiny", log=lambda s: None, stop_after=14)
    r = fit(sfm, tmp_path / "r.ply", cfg, dataset_root="tiny", log=lambda s: None, resume=True)
    fit(sfm, tmp_path / "u.ply", cfg, dataset_root="tiny", log=lambda s: None)
    assert r.extra_meta["fit"]["density"]["chose"] == "extent" and r.extra_meta["fit"]["config"]["voxel_rule"] == \
        "extent"
    assert (tmp_path / "r.ply").read_bytes() == (tmp_path / "u.ply").read_bytes()


def test_cli_fit_and_eval(tiny_dataset, tmp_path):
    from click.testing import CliRunner
    from proxycodec.cli.main import cli

    out = tmp_path / "s.ply"
    r = CliRunner().invoke(cli, ["fit", str(tiny_dataset), "-o", str(out), "--iters", "6", "--init-points", "300",
                                 "--no-proxies", "--max-width", "24"])
    assert r.exit_code == 0, r.output
    assert out.exists()
    r = CliRunner().invoke(cli, ["eval", str(out), str(tiny_dataset), "-o", str(tmp_path / "ev"),
                                 "--res", "0.1,0.5,1.0,1.5", "--views", "1"])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert [d["xi"] for d in rep["per_resolution"]] == [0.1, 0.5, 1.0, 1.5]
    assert rep["per_resolution"][2]["width"] == 24  # the scene's own --max-width is the default
    assert all(math.isfinite(d["psnr"]) for d in rep["per_resolution"])
    assert "LPIPS" in rep["lpips"]
    for name in ("eval.md", "psnr_ssim_vs_resolution.png", "crops.png"):
        assert (tmp_path / "ev" / name).stat().st_size > 0


def test_cli_fit_on_sigterm_keeps_a_checkpoint_and_resumes(tiny_dataset, tmp_path):
    """SIGTERM (a scheduler's stop, `kill`) stops `fit` as Ctrl-C does: the checkpoint is written, no output, one line
    and exit 143; `--resume` then finishes from it."""
    import signal

    out = tmp_path / "s.ply"
    args = [sys.executable, "-m", "proxycodec.cli", "--threads", "1", "fit", str(tiny_dataset), "-o", str(out),
            "--init-points", "300", "--no-proxies", "--max-width", "24", "--checkpoint-every", "0"]
    p = subprocess.Popen([*args, "--iters", "1000000"], stderr=subprocess.PIPE, text=True)
    seen = []  # up to the first progress line: training has started
    _, err = signal_when_ready(p, signal.SIGTERM, lambda: seen.extend(read_until(p.stderr, "it ")))
    assert p.returncode == 143, "".join(seen) + err
    lines = err.splitlines()
    assert "Traceback" not in err and lines[-1] == "terminated (SIGTERM)", err
    assert re.fullmatch(r"checkpoint saved at iteration \d+: .*s\.ckpt\.pxc \(continue with --resume\)", lines[-2])
    saved = int(lines[-2].split()[4].rstrip(":"))
    assert not out.exists() and (tmp_path / "s.ckpt.pxc").exists()
    r = subprocess.run([*args, "--iters", str(saved + 2), "--resume"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert f"resumed from {tmp_path / 's.ckpt.pxc'} at iteration {saved}" in r.stderr
    assert f"done: {saved + 2} iterations" in r.stderr
    assert out.exists() and not (tmp_path / "s.ckpt.pxc").exists()


def test_cli_fit_bad_dataset(tmp_path):
    from click.testing import CliRunner
    from proxycodec.cli.main import cli

    r = CliRunner().invoke(cli, ["fit", str(tmp_path), "-o", str(tmp_path / "x.ply"), "--iters", "2"])
    assert r.exit_code == 2 and "not a dataset" in r.output


def test_stage2_predicts_every_leaf_it_renders(data, monkeypatch):
    """On the rate term's quantisation grids the anchors' extents move, and with them the frustum test: the leaves
    whose rows are predicted are those of the render's own visibility, so no drawn leaf renders its stored feature
    (what the container, which stores no leaf features, could never show)."""
    import dataclasses

    import proxycodec.train as train_mod
    from proxycodec.train import Trainer

    tr = Trainer(data, small_config(iters=20, lambda_rate=1e-4), "tiny")
    while tr.stage < 2:
        tr.train_step()
    assert tr.rate is not None
    rate = tr.rate.forward

    def wider(*a, **kw):  # exaggerates what the grids do to the extents, so that the frustum test differs
        f, o, s, bits = rate(*a, **kw)
        return f, o, s + 2.0, bits

    monkeypatch.setattr(tr.rate, "forward", wider)
    # zoomed in 3x, each view sees part of the scene: the frustum test has anchors to tell apart
    zoomed = type(tr.data.cameras)(dataclasses.replace(c, fx=3 * c.fx, fy=3 * c.fy) for c in tr.data.cameras)
    tr.data = dataclasses.replace(tr.data, cameras=zoomed)
    checked = []
    render = train_mod.render_scene

    def spy(scene, decoder, cam, xi, **kw):
        r = render(scene, decoder, cam, xi, **kw)
        vis = r.visible_anchor_index
        drawn = vis[~tr.proxy_mask[vis]]
        with torch.no_grad():
            want, _ = tr.predictor.predict(tr.anchors.positions, scene.features, tr.nearest, drawn)
        assert torch.equal(kw["features"][drawn], want)  # the same computation on the same rows
        checked.append((len(drawn), len(vis), tr.anchors.num_anchors))
        return r

    monkeypatch.setattr(train_mod, "render_scene", spy)
    for _ in range(4):
        tr.train_step()
    assert len(checked) == 4 and all(d > 0 for d, _, _ in checked)


def test_a_training_step_synchronises_three_times(data):
    """What makes a GPU wait for the host: data-dependent sizes and values read back. A stage-1 and a stage-2 step
    (rate term on) each have three (the frustum test, the decoder's live anchors and live slots; the CPU path's
    projection adds none), so no ``.item()``, no second frustum test and no host read of a loss creeps back in."""
    from proxycodec.bench.ops import dispatch_counter
    from proxycodec.train import Trainer

    syncing = {"nonzero", "_local_scalar_dense", "is_nonzero", "masked_select", "unique", "_unique2", "item"}
    tr = Trainer(data, small_config(iters=20, lambda_rate=1e-4, update_interval=1000), "tiny")
    per_stage = {}
    while tr.stage < 2 or 2 not in per_stage:
        stage = tr.stage
        with dispatch_counter() as c:
            tr.train_step()
        if tr.stage == stage:  # not the step that entered stage 2 (its setup reads the host on purpose)
            per_stage.setdefault(stage, [n for n in c.names if n in syncing])
    assert tr.rate is not None
    assert per_stage == {1: ["nonzero"] * 3, 2: ["nonzero"] * 3}, per_stage


def test_a_stage2_step_runs_each_rate_net_once_and_encodes_no_proxy_vector(data, monkeypatch):
    """The launches a stage-2 step saves stay saved: the rate term calls each of its three nets once (its passes
    stacked), and the predictor takes its proxy -> leaf encodings from the table made at the stage switch."""
    from proxycodec import entropy_fit, proxy
    from proxycodec.train import Trainer

    tr = Trainer(data, small_config(iters=20, lambda_rate=1e-4, update_interval=1000, predictor_context=2), "tiny")
    while tr.stage < 2:
        tr.train_step()
    assert tr.encodings is not None and tr.encodings.shape[1:] == (2, tr.predictor.config.n_geo)
    calls = {"nets": 0, "encodings": 0}
    net_forward, inputs = entropy_fit.FloatNet.forward, proxy.predictor_inputs

    def count_net(self, *a, **k):
        calls["nets"] += 1
        return net_forward(self, *a, **k)

    def count_inputs(*a, **k):
        calls["encodings"] += 1
        return inputs(*a, **k)

    monkeypatch.setattr(entropy_fit.FloatNet, "forward", count_net)
    monkeypatch.setattr(proxy, "predictor_inputs", count_inputs)
    tr.train_step()
    assert calls == {"nets": 3, "encodings": 0}, calls


def test_the_leaf_ramp_passes_the_leaves_from_their_own_features_to_the_predictions(data):
    """``leaf_ramp``: the leaves' rendered features start stage 2 as their own values, are the linear blend
    (1 - t) own + t predicted at t = (stage-2 progress) / ramp, and the predictions alone from the end of the ramp
    on; without a ramp the predictions at once. Fractions outside [0, 1) are one-line errors."""
    import torch

    from proxycodec.errors import ProxycodecError
    from proxycodec.train import FitConfig, Trainer

    for bad in (-0.1, 1.0):
        with pytest.raises(ProxycodecError, match="ramp"):
            FitConfig(leaf_ramp=bad)
    cfg = small_config(iters=40, update_interval=1000, leaf_ramp=0.5)
    assert FitConfig.from_json(cfg.to_json()) == cfg
    tr = Trainer(data, cfg, "tiny")
    while tr.stage < 2:
        tr.train_step()
    a = tr.anchors
    vis = torch.arange(a.num_anchors)
    leaves = tr.leaves
    own = a.features.detach()[leaves]
    pred, _ = tr.predictor.predict(a.positions, a.features, tr.nearest, leaves, None, tr.encodings)
    for it, t in ((20, 0.0), (25, 0.5), (30, 1.0), (35, 1.0)):  # stage 2 is iterations 20..40; the ramp ends at 30
        tr.iteration = it
        assert tr.leaf_blend() == pytest.approx(t)
        feats, _, _ = tr.leaf_tables(vis, with_recon=False)
        torch.testing.assert_close(feats[leaves], (1 - t) * own + t * pred.detach(), rtol=0, atol=1e-6)
        proxies = tr.proxy_mask.nonzero().squeeze(1)
        assert torch.equal(feats[proxies], a.features.detach()[proxies])
    tr.cfg = small_config(iters=40, update_interval=1000)  # no ramp: the predictions from the switch on
    tr.iteration = 20
    assert tr.leaf_blend() == 1.0
