"""The plain 3DGS baseline (``proxycodec fit --explicit``, ``proxycodec.explicit``).

A tiny Blender-format dataset is made once per module: six coloured Gaussians rendered (with the project's own
rasterizer, no gate) from 8 + 2 orbit cameras at 24x24 px. Runs are a few dozen iterations.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import write_blender

pytestmark = pytest.mark.usefixtures("one_thread")

SIZE = 24


# ------------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def tiny_blender(tmp_path_factory) -> Path:
    from proxycodec.camera import orbit_cameras
    from proxycodec.explicit import NO_GATE
    from proxycodec.render import render_gaussians

    root = tmp_path_factory.mktemp("tiny_explicit")
    means = torch.tensor([[0.0, 0.0, 0.0], [0.35, 0.0, 0.1], [-0.3, 0.25, 0.0], [0.0, -0.3, 0.3],
                          [0.2, 0.3, -0.25], [-0.25, -0.2, -0.2]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 6)
    scales = torch.tensor([[0.15, 0.08, 0.1], [0.06, 0.12, 0.06], [0.1, 0.1, 0.05], [0.08, 0.05, 0.12],
                           [0.1, 0.06, 0.06], [0.07, 0.1, 0.09]])
    ops = torch.full((6,), 0.9)
    cols = torch.tensor([[0.9, 0.1, 0.1], [0.1, 0.8, 0.2], [0.1, 0.2, 0.9], [0.9, 0.8, 0.1],
                         [0.6, 0.1, 0.7], [0.1, 0.7, 0.7]])
    cams = orbit_cameras((0.0, 0.0, 0.0), 2.5, 10, elevation_deg=30.0, fov_x_deg=40.0, width=SIZE, height=SIZE)
    splits = {"train": [c for i, c in enumerate(cams) if i % 5 != 0],
              "test": [c for i, c in enumerate(cams) if i % 5 == 0]}
    return write_blender(root, splits, lambda cam: render_gaussians(means, quats, scales, ops, cols, cam, gate=NO_GATE,
                                                                    backend="reference").image)


@pytest.fixture(scope="module")
def data(tiny_blender):
    from proxycodec.formats.datasets import load_dataset

    return load_dataset(tiny_blender)


def small_config(**kw):
    from proxycodec.explicit import ExplicitConfig

    base = {"iters": 40, "max_width": None, "init_points": 200, "seed": 1, "log_every": 1e9,
            "densify_interval": 10, "sh_degree": 1}
    base.update(kw)
    return ExplicitConfig(**base)


def _mean_train_loss(tr) -> float:
    from proxycodec.metrics import dssim

    out = []
    with torch.no_grad():
        for i in tr.data.train_indices:
            img = tr.render(tr.data.cameras[i], tr.cfg.sh_degree).image
            gt = tr.data.load_image(i, 1.0)
            out.append(float(0.8 * (img - gt).abs().mean() + 0.2 * dssim(img, gt)))
    return float(np.mean(out))


# ------------------------------------------------------------------------------------------------ SH
class TestSH:
    def test_degree0_is_c0_times_dc(self):
        from proxycodec.explicit import SH_C0, eval_sh, sh_colors

        sh = torch.tensor([[[1.0, -2.0, 0.5]]])
        d = torch.tensor([[0.0, 0.0, 1.0]])
        assert torch.allclose(eval_sh(0, sh, d), torch.tensor([[SH_C0, -2 * SH_C0, 0.5 * SH_C0]]))
        # sh_colors adds 0.5 and clamps at 0 (3DGS), whatever the view direction
        c = sh_colors(sh, torch.tensor([[1.0, 2.0, 3.0]]), np.array([0.0, 0.0, 0.0]), 0)
        assert torch.allclose(c, torch.tensor([[0.5 + SH_C0, 0.0, 0.5 + 0.5 * SH_C0]]))

    def test_degree1_by_hand(self):
        from proxycodec.explicit import eval_sh

        C0, C1 = 0.28209479177387814, 0.4886025119029199
        sh = torch.zeros(1, 4, 3)
        sh[0, 0] = torch.tensor([0.2, 0.0, 0.0])
        sh[0, 1] = torch.tensor([1.0, 0.0, 0.0])  # times -C1 y
        sh[0, 2] = torch.tensor([0.0, 1.0, 0.0])  # times +C1 z
        sh[0, 3] = torch.tensor([0.0, 0.0, 1.0])  # times -C1 x
        x, y, z = 0.6, 0.0, 0.8
        got = eval_sh(1, sh, torch.tensor([[x, y, z]]))[0]
        want = torch.tensor([0.2 * C0 - C1 * y, C1 * z, -C1 * x])
        assert torch.allclose(got, want, atol=1e-7)
        # direction is from the camera centre to the Gaussian
        from proxycodec.explicit import sh_colors

        c = sh_colors(sh, torch.tensor([[0.6, 0.0, 0.8]]) * 5, np.zeros(3), 1)[0]
        assert torch.allclose(c, (want + 0.5).clamp_min(0), atol=1e-6)
        # degree 1 asked of degree-0 coefficients is an error
        from proxycodec.errors import ProxycodecError

        with pytest.raises(ProxycodecError):
            eval_sh(1, sh[:, :1], torch.tensor([[x, y, z]]))


# ------------------------------------------------------------------------------------------------ densification
def _params(n_extra_low=0):
    # 0: small, high grad -> clone; 1: big, high grad -> split; 2: small, low grad -> kept; 3: transparent -> pruned
    means = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    scales = torch.log(torch.tensor([[0.01, 0.01, 0.01], [0.5, 0.1, 0.1], [0.01, 0.01, 0.01], [0.01, 0.01, 0.01]]))
    op = torch.tensor([2.0, 2.0, 2.0, -8.0])  # sigmoid(-8) = 3.4e-4 < 0.005
    return {"means": means, "sh_dc": torch.arange(12.0).reshape(4, 1, 3), "sh_rest": torch.zeros(4, 3, 3),
            "opacities": op, "scales": scales, "quats": torch.tensor([[1.0, 0, 0, 0]] * 4)}


def test_densify_clones_splits_and_prunes():
    from proxycodec.explicit import densify_and_prune

    p = _params()
    grads = torch.tensor([1e-3, 1e-3, 1e-5, 0.0])
    r = densify_and_prune(p, grads, grad_threshold=2e-4, percent_dense=0.01, extent=4.0, prune_opacity=0.005,
                          prune_big_world=None, max_gaussians=100, rng=np.random.default_rng(0))
    assert (r.n_clone, r.n_split, r.n_pruned) == (1, 1, 1)
    q = r.params
    # old set minus the split parent (0, 2, 3), then the clone of 0, then two children of 1; then 3 is pruned
    assert q["means"].shape[0] == 5
    assert torch.equal(q["means"][0], p["means"][0]) and torch.equal(q["means"][1], p["means"][2])
    assert torch.equal(q["means"][2], p["means"][0])  # the clone: an exact copy
    assert torch.equal(q["sh_dc"][2], p["sh_dc"][0])
    kids = q["means"][3:]
    assert not torch.equal(kids[0], kids[1])
    assert (kids - p["means"][1]).abs().max() < 4 * 0.5  # sampled around the parent with its scales
    assert torch.allclose(torch.exp(q["scales"][3:]), torch.exp(p["scales"][1]).expand(2, 3) / 1.6)
    assert torch.equal(q["sh_dc"][3], p["sh_dc"][1]) and torch.equal(q["opacities"][3:], p["opacities"][[1, 1]])
    assert torch.equal(r.keep_old, torch.tensor([0, 2, 3])) and r.n_new == 3
    assert torch.equal(r.keep_final, torch.tensor([0, 1, 3, 4, 5]))


def test_densify_below_threshold_and_cap():
    from proxycodec.explicit import densify_and_prune

    p = _params()
    r = densify_and_prune(p, torch.full((4,), 1e-4), grad_threshold=2e-4, percent_dense=0.01, extent=4.0,
                          prune_opacity=0.005, prune_big_world=None, max_gaussians=100, rng=np.random.default_rng(0))
    assert (r.n_clone, r.n_split) == (0, 0) and r.params["means"].shape[0] == 3  # only the pruning
    # cap: room for one more Gaussian -> only the highest gradient (the big one) is densified
    r = densify_and_prune(p, torch.tensor([1e-3, 2e-3, 0, 0]), grad_threshold=2e-4, percent_dense=0.01,
                          extent=4.0, prune_opacity=0.0, prune_big_world=None, max_gaussians=5,
                          rng=np.random.default_rng(0))
    assert (r.n_clone, r.n_split) == (0, 1) and r.params["means"].shape[0] == 5
    # world-space pruning of big Gaussians
    r = densify_and_prune(p, torch.zeros(4), grad_threshold=2e-4, percent_dense=0.01, extent=4.0,
                          prune_opacity=0.0, prune_big_world=0.1, max_gaussians=100, rng=np.random.default_rng(0))
    assert torch.equal(r.params["means"], p["means"][[0, 2, 3]])  # Gaussian 1 (0.5 > 0.1 x 4) is gone


def test_cli_max_gaussians_reaches_the_config(tiny_blender, tmp_path, monkeypatch):
    """``--max-gaussians`` sets the densification cap; left out, ExplicitConfig's guard applies."""
    from click.testing import CliRunner
    import proxycodec.explicit as explicit
    from proxycodec.cli.main import cli

    seen = []

    def fake_run(data, cfg, log, out, **kw):
        seen.append(cfg.max_gaussians)
        raise explicit.ProxycodecError("stop here")

    monkeypatch.setattr(explicit, "run_explicit", fake_run)
    base = ["fit", str(tiny_blender), "--explicit", "-o", str(tmp_path / "e.ply"), "--iters", "2", "--max-width", "20"]
    for extra in (["--max-gaussians", "1234"], []):
        r = CliRunner().invoke(cli, base + extra)
        assert r.exit_code == 2 and "stop here" in r.output, r.output
    assert seen == [1234, explicit.ExplicitConfig.max_gaussians]
    r = CliRunner().invoke(cli, base + ["--max-gaussians", "0"])
    assert r.exit_code == 2 and "--max-gaussians" in r.output


# ------------------------------------------------------------------------------------------------ training
def test_training_reduces_loss_and_densifies(data):
    from proxycodec.explicit import ExplicitTrainer

    tr = ExplicitTrainer(data, small_config(iters=60, grad_threshold=1e-5))
    before = _mean_train_loss(tr)
    n0 = tr.num_gaussians
    log = []
    tr.log = log.append
    while not tr.done():
        tr.train_step()
    after = _mean_train_loss(tr)
    assert after < 0.8 * before, (before, after)
    assert any("densify" in s for s in log) and tr.num_gaussians != n0
    for k, t in tr.params.items():  # optimiser state follows the rows
        assert tr.opt.m[k].shape == t.shape and tr.opt.params[k] is t


def test_ply_round_trip_and_eval_model(data, tmp_path):
    from proxycodec.formats.inria_ply import read_inria_ply

    from proxycodec.explicit import ExplicitModel, is_inria_ply, run_explicit

    out = tmp_path / "g.ply"
    tr = run_explicit(data, small_config(iters=15), log=None, out=out)
    ply = tr.result()
    back = read_inria_ply(out)
    assert back == ply and back.sh_degree == 1 and back.has_normals
    assert is_inria_ply(out)
    m = ExplicitModel.load(out, background=data.background)
    assert m.scene.num_anchors is None and m.num_gaussians == ply.n_gaussians
    cam = data.cameras[data.test_indices[0]]
    r = m.render(cam, 0.5)
    assert r.image.shape == (SIZE // 2, SIZE // 2, 3) and r.projected.count > 0
    with torch.no_grad():
        ref = tr.render(cam, 1).image
    assert torch.allclose(m.render(cam, 1.0).image, ref, atol=1e-5)  # what was trained is what is rendered


def test_deterministic_for_seed_and_iters(data, tmp_path):
    from proxycodec.explicit import train_explicit

    cfg = small_config(iters=30, grad_threshold=1e-5)
    train_explicit(data, cfg, log=None, out=tmp_path / "a.ply")
    train_explicit(data, cfg, log=None, out=tmp_path / "b.ply")
    assert (tmp_path / "a.ply").read_bytes() == (tmp_path / "b.ply").read_bytes()
    train_explicit(data, small_config(iters=30, grad_threshold=1e-5, seed=2), log=None, out=tmp_path / "c.ply")
    assert (tmp_path / "a.ply").read_bytes() != (tmp_path / "c.ply").read_bytes()


def test_interrupted_and_resumed_writes_the_same_ply(data, tmp_path):
    """A run interrupted (its checkpoint written) and resumed writes the PLY of the same run straight through, byte
    for byte: Gaussians, Adam moments, densification statistics, view order and random stream all continue; the
    checkpoint is removed after success."""
    from proxycodec.explicit import run_explicit
    from proxycodec.loop import checkpoint_path_for

    cfg = small_config(iters=36, grad_threshold=1e-5)
    straight = run_explicit(data, cfg, log=None, out=tmp_path / "a.ply")
    out = tmp_path / "b.ply"
    log = []
    with pytest.raises(KeyboardInterrupt):
        run_explicit(data, cfg, log=log.append, out=out, stop_after=15)  # after the densification at 10
    ckpt = checkpoint_path_for(out)
    assert ckpt.exists() and not out.exists() and any("checkpoint saved at iteration 15" in s for s in log)
    with pytest.raises(KeyboardInterrupt):  # a second interruption, from the resumed state (past the one at 20)
        run_explicit(data, cfg, log=None, out=out, resume=True, stop_after=8)
    resumed = run_explicit(data, cfg, log=log.append, out=out, resume=True)
    assert any("resumed from" in s and "at iteration 23" in s for s in log)
    assert resumed.iteration == straight.iteration == 36
    assert straight.num_gaussians != 200  # densification ran in both parts
    assert out.read_bytes() == (tmp_path / "a.ply").read_bytes()
    assert not ckpt.exists()


def test_resume_refuses_other_settings_and_missing_checkpoints(data, tmp_path):
    from proxycodec.errors import ProxycodecError
    from proxycodec.explicit import run_explicit
    from proxycodec.loop import checkpoint_path_for

    out = tmp_path / "c.ply"
    with pytest.raises(ProxycodecError, match="no checkpoint to resume from"):
        run_explicit(data, small_config(iters=10), log=None, out=out, resume=True)
    with pytest.raises(KeyboardInterrupt):
        run_explicit(data, small_config(iters=10), log=None, out=out, stop_after=3)
    with pytest.raises(ProxycodecError, match=r"c\.ckpt\.pxc.*different settings \(sh_degree\)"):
        run_explicit(data, small_config(iters=10, sh_degree=2), log=None, out=out, resume=True)
    with pytest.raises(ProxycodecError, match=r"different settings \(antialiased\)"):
        run_explicit(data, small_config(iters=10, antialiased=True), log=None, out=out, resume=True)
    # the run length may change: 3 done + 4 more
    tr = run_explicit(data, small_config(iters=7, max_gaussians=500), log=None, out=out, resume=True,
                      keep_checkpoint=True)
    assert tr.iteration == 7 and out.exists() and checkpoint_path_for(out).exists()
    checkpoint_path_for(out).write_bytes(b"not a container")
    with pytest.raises(ProxycodecError, match=r"c\.ckpt\.pxc"):
        run_explicit(data, small_config(iters=10), log=None, out=out, resume=True)


def test_antialiased_training_renders_with_the_compensation(data):
    """`fit --explicit --antialiased`: the trainer renders its Gaussians with the antialiased filter's compensation
    (gsplat's antialiased mode), which differs from the plain render of the same Gaussians."""
    from proxycodec.explicit import NO_GATE_ANTIALIASED, ExplicitTrainer, sh_colors
    from proxycodec.render import render_gaussians

    cam = data.cameras[data.train_indices[0]]
    tr = ExplicitTrainer(data, small_config(iters=4, antialiased=True))
    q = tr.params
    with torch.no_grad():
        got = tr.render(cam, 1).image
        sh = torch.cat([q["sh_dc"], q["sh_rest"][:, :3]], 1)
        want = render_gaussians(q["means"], q["quats"], torch.exp(q["scales"]), torch.sigmoid(q["opacities"]),
                                sh_colors(sh, q["means"], cam.center, 1), cam, background=tr.bg,
                                gate=NO_GATE_ANTIALIASED, backend=tr.cfg.backend).image
        plain = ExplicitTrainer(data, small_config(iters=4)).render(cam, 1).image
    assert torch.equal(got, want) and not torch.equal(got, plain)


def test_random_resolution_option(data):
    from proxycodec.explicit import ExplicitTrainer

    tr = ExplicitTrainer(data, small_config(iters=6, random_res=True, xi_min=0.5))
    xis = [tr.train_step()["xi"] for _ in range(6)]
    assert all(0.5 <= x <= 1.0 for x in xis) and len(set(xis)) > 1


def test_config_validation():
    from proxycodec.errors import ProxycodecError
    from proxycodec.explicit import ExplicitConfig

    for kw in ({"sh_degree": 4}, {"iters": None}, {"iters": 0}, {"time_budget": -1.0}):
        with pytest.raises(ProxycodecError):
            ExplicitConfig(**kw)


# ------------------------------------------------------------------------------------------------ CLI
def test_cli_fit_explicit_then_eval(tiny_blender, tmp_path):
    from click.testing import CliRunner
    from proxycodec.cli.main import cli
    from proxycodec.formats.inria_ply import read_inria_ply

    out = tmp_path / "e.ply"
    r = CliRunner().invoke(cli, ["fit", str(tiny_blender), "--explicit", "-o", str(out), "--iters", "12",
                                 "--init-points", "150", "--max-width", "20", "--sh-degree", "2"])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.ply"]  # just the PLY
    assert read_inria_ply(out).sh_degree == 2
    r = CliRunner().invoke(cli, ["eval", str(out), str(tiny_blender), "-o", str(tmp_path / "ev"),
                                 "--max-width", "20", "--res", "0.5,1.0", "--views", "1"])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "ev" / "eval.json").read_text())
    assert [d["width"] for d in rep["per_resolution"]] == [10, 20]
    assert all(math.isfinite(d["psnr"]) for d in rep["per_resolution"])
    assert rep["summary"]["anchors"] is None and rep["summary"]["gaussians_stored"] > 0
    assert "explicit Gaussians" in (tmp_path / "ev" / "eval.md").read_text()
    r = CliRunner().invoke(cli, ["eval", str(out), str(tiny_blender), "-o", str(tmp_path / "evj"),
                                 "--max-width", "20", "--res", "0.5,1.0", "--views", "1", "--json"])
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout) == json.loads((tmp_path / "evj" / "eval.json").read_text())  # stdout: the JSON alone
    r = CliRunner().invoke(cli, ["eval", str(out), str(tiny_blender), "-o", str(tmp_path / "ev2"),
                                 "--max-width", "20", "--res", "0.5,1.0", "--views", "1", "--supersample", "2"])
    assert r.exit_code == 0, r.output
    rep2 = json.loads((tmp_path / "ev2" / "eval.json").read_text())
    assert [d["width"] for d in rep2["per_resolution"]] == [10, 20] and rep2["summary"]["supersample"] == 2
    assert rep["summary"]["supersample"] == 1
    assert "2 x 2 samples per pixel" in (tmp_path / "ev2" / "eval.md").read_text()
    assert [d["psnr"] for d in rep2["per_resolution"]] != [d["psnr"] for d in rep["per_resolution"]]
    r = CliRunner().invoke(cli, ["fit", str(tiny_blender), "--explicit", "-o", str(out), "--iters", "2", "--resume"])
    assert r.exit_code == 2 and "no checkpoint to resume from" in r.output and "e.ckpt.pxc" in r.output


def test_a_file_flagged_antialiased_renders_with_the_compensation(tmp_path):
    """An SPZ with flag 0x1 (trained with Mip-Splatting's / gsplat's antialiased filter) renders with its opacity
    compensation; the same Gaussians unflagged render as plain 3DGS, brighter where they are sub-pixel."""
    from proxycodec.camera import Camera
    from proxycodec.explicit import NO_GATE, NO_GATE_ANTIALIASED, ExplicitModel, sh_colors
    from proxycodec.formats.inria_ply import GaussianPly
    from proxycodec.formats.spz import write_spz
    from proxycodec.render import render_gaussians

    rng = np.random.default_rng(4)
    n = 300
    ply = GaussianPly(means=rng.uniform(-0.5, 0.5, (n, 3)), sh=rng.uniform(-0.5, 0.5, (n, 1, 3)),
                      opacities=rng.uniform(0, 3, n), scales=rng.uniform(-7, -4, (n, 3)), quats=rng.normal(size=(n, 4)))
    for aa in (True, False):
        write_spz(tmp_path / f"{aa}.spz", ply, antialiased=aa)
    cam = Camera.look_at([0, -3, 0], [0, 0, 0], width=64, height=48)
    flagged = ExplicitModel.load(tmp_path / "True.spz", background=(0.0, 0.0, 0.0))
    plain = ExplicitModel.load(tmp_path / "False.spz", background=(0.0, 0.0, 0.0))
    assert flagged.antialiased and flagged.gate == NO_GATE_ANTIALIASED and flagged.meta["antialiased"]
    assert not plain.antialiased and plain.gate == NO_GATE
    a, b = flagged.render(cam).image, plain.render(cam).image
    m = flagged
    colors = sh_colors(m._sh, m._means, cam.center, m.ply.sh_degree)
    want = render_gaussians(m._means, m._quats, m._scales, m._op, colors, cam, background=(0.0, 0.0, 0.0),
                            gate=NO_GATE_ANTIALIASED).image
    assert torch.equal(a, want)
    assert b.sum() > 1.5 * a.sum() > 0  # sub-pixel Gaussians deposit far less with the compensation


def test_antialiased_mode_forces_the_compensation_on_either_kind_of_scene():
    """``apply_antialiased_mode``: "scene" leaves a model as it is, "on" / "off" force it, on a plain 3DGS model
    (its ``antialiased``) and an anchor scene (its decoder's gate) alike; anything else is refused."""
    from proxycodec.errors import ProxycodecError
    from proxycodec.explicit import ExplicitModel
    from proxycodec.formats.inria_ply import GaussianPly
    from proxycodec.model import apply_antialiased_mode
    from proxycodec.sample import sample_model

    rng = np.random.default_rng(5)
    ex = ExplicitModel(GaussianPly(means=rng.normal(size=(8, 3)), sh=np.zeros((8, 1, 3)), opacities=np.zeros(8),
                                   scales=np.full((8, 3), -3.0), quats=rng.normal(size=(8, 4))))
    anchors = sample_model()
    for model, get in ((ex, lambda m: m.antialiased), (anchors, lambda m: m.decoder.config.gate.antialiased)):
        assert apply_antialiased_mode(model, "scene") is False and get(model) is False
        assert apply_antialiased_mode(model, "on") is True and get(model) is True
        assert apply_antialiased_mode(model, "scene") is True
        assert apply_antialiased_mode(model, "off") is False and get(model) is False
        with pytest.raises(ProxycodecError, match="scene, on or off"):
            apply_antialiased_mode(model, "yes")
    assert anchors.decoder.config.gate.enabled  # the gate itself is left alone
