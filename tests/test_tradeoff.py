"""Issue #7: the ablation switches of ``fit`` / ``eval``, the Pareto front, and ``proxycodec bench`` end to end.

Everything is tiny and synthetic: a Blender-format dataset rendered from part of the built-in sample scene at 24 px
(6 training + 2 test views), fits of a few dozen iterations.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import load_benchmark, write_blender

from proxycodec.camera import orbit_cameras
from proxycodec.errors import ProxycodecError

pytestmark = pytest.mark.usefixtures("one_thread")
SIZE = 24


# ------------------------------------------------------------------------------------------------ fixtures
def _tiny_scene():
    from proxycodec.model import SceneModel
    from proxycodec.sample import sample_model

    m = sample_model()
    s = m.scene
    lo, hi = torch.tensor([0.15, -0.85, -0.05]), torch.tensor([0.95, -0.05, 0.6])
    sub = s.subset(((s.positions >= lo) & (s.positions <= hi)).all(1).nonzero().squeeze(1))
    sub = sub.subset(torch.arange(0, sub.num_anchors, 2))  # a few hundred anchors
    return SceneModel(sub, m.decoder)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """(dataset folder, anchor PLY of the scene that rendered it)."""
    root = tmp_path_factory.mktemp("tiny_tradeoff")
    model = _tiny_scene()
    cams = orbit_cameras((0.55, -0.45, 0.2), 1.8, 8, elevation_deg=35.0, fov_x_deg=45.0, width=SIZE, height=SIZE)
    splits = {"train": [c for i, c in enumerate(cams) if i % 4 != 0],
              "test": [c for i, c in enumerate(cams) if i % 4 == 0]}
    data = write_blender(root / "data", splits, lambda cam: model.render(cam, 1.0).image)
    model.cameras = list(cams)
    ply, _ = model.save(root / "scene.ply")
    return data, ply


def small_config(**kw):
    from proxycodec.train import FitConfig

    base = {"iters": 24, "max_width": None, "init_points": 200, "update_interval": 10, "predictor_warmup": 5,
            "predictor_hidden": 16, "predictor_blocks": 1, "checkpoint_every": 0, "log_every": 1e9, "seed": 3}
    base.update(kw)
    return FitConfig(**base)


def _fit(data_dir, out, cfg):
    from proxycodec.formats.datasets import load_dataset

    from proxycodec.train import fit

    return fit(load_dataset(data_dir), out, cfg, dataset_root="tiny", log=lambda s: None)


# ------------------------------------------------------------------------------------------------ L_recon
class TestReconLoss:
    def test_variants_match_hand_computation(self):
        from proxycodec.proxy import recon_loss

        pred = torch.tensor([[1.0, 2.0, 0.0], [0.0, -1.0, 1.0]])
        tgt = torch.tensor([[1.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
        mse = ((0 + 4 + 0) + (1 + 4 + 0)) / 2  # row sums of squares, mean over rows
        l1 = ((0 + 2 + 0) + (1 + 2 + 0)) / 2
        cos0 = 1.0 / math.sqrt(5.0)  # <(1,2,0),(1,0,0)> / (sqrt5 * 1)
        cos1 = 0.0  # <(0,-1,1),(1,1,1)> = 0
        ours = mse + 0.1 * ((1 - cos0) + (1 - cos1)) / 2
        assert float(recon_loss(pred, tgt, kind="mse")) == pytest.approx(mse)
        assert float(recon_loss(pred, tgt, kind="l1")) == pytest.approx(l1)
        assert float(recon_loss(pred, tgt)) == pytest.approx(ours)
        assert float(recon_loss(pred, tgt, kind="mse+cos")) == pytest.approx(ours)
        with pytest.raises(ProxycodecError, match="unknown reconstruction loss"):
            recon_loss(pred, tgt, kind="huber")

    def test_fit_config_validates_the_switches(self):
        for bad in ({"recon_loss": "huber"}, {"predictor": "attention"}, {"lambda_recon_fixed": -1.0},
                    {"gate_kappa": 0.0}, {"gate_eta": math.nan}):
            with pytest.raises(ProxycodecError):
                small_config(**bad)

    def test_lambda_recon_fixed_replaces_the_schedule(self, tiny):
        from proxycodec.formats.datasets import load_dataset

        from proxycodec.train import Trainer

        data = load_dataset(tiny[0])
        default = Trainer(data, small_config(), "tiny")  # [D] 0: rendering alone drives joint stage 2
        assert (default.lambda_recon(0.6), default.lambda_recon(0.9)) == (0.0, 0.0)
        sched = Trainer(data, small_config(lambda_recon_fixed=None), "tiny")  # the paper's schedule
        assert (sched.lambda_recon(0.6), sched.lambda_recon(0.7)) == (0.1, 0.01)
        fixed = Trainer(data, small_config(lambda_recon_fixed=0.1), "tiny")
        assert (fixed.lambda_recon(0.6), fixed.lambda_recon(0.9)) == (0.1, 0.1)

    def test_predictor_training_uses_the_chosen_loss(self):
        from proxycodec.proxy import PredictorConfig, ResidualPredictor, TrainConfig, train_predictor

        g = torch.Generator().manual_seed(0)
        pos = torch.rand(60, 3, generator=g)
        feats = torch.randn(60, 8, generator=g)
        mask = np.zeros(60, bool)
        mask[::3] = True
        finals = {}
        for kind in ("mse+cos", "mse", "l1"):
            torch.manual_seed(0)
            p = ResidualPredictor(PredictorConfig(feat_dim=8, n_offsets=2, hidden=8, n_blocks=1, dist_ref=0.05))
            finals[kind] = train_predictor(p, pos, feats, mask, config=TrainConfig(iters=20, seed=0), recon=kind)
        assert len({round(r.final_loss, 6) for r in finals.values()}) == 3
        assert finals["l1"].baseline_loss != finals["mse"].baseline_loss


# ------------------------------------------------------------------------------------------------ Proxy&Leaf MLP
class TestProxyLeafMLP:
    def test_shapes_json_and_arrays_round_trip(self):
        from proxycodec.proxy import ProxyLeafConfig, ProxyLeafMLP, predictor_from_json

        cfg = ProxyLeafConfig(feat_dim=8, n_offsets=2, hidden=16, n_blocks=1, pe_pos_freqs=3,
                              scene_center=(0.5, 0.0, 0.0), scene_radius=2.0)
        torch.manual_seed(0)
        p = ProxyLeafMLP(cfg)
        g = torch.Generator().manual_seed(1)
        pos, feats = torch.rand(10, 3, generator=g), torch.randn(10, 8, generator=g)
        nearest, leaves = torch.zeros(10, dtype=torch.long), torch.arange(1, 10)
        out, offs = p.predict(pos, feats, nearest, leaves)
        assert out.shape == (9, 8) and offs is None
        assert p.geometry(pos[leaves], pos[nearest[leaves]]).shape == (9, 2 * 3 * (1 + 2 * 3))
        # the leaf is an input (its position), and the output is not a residual on the proxy feature
        out2, _ = p.predict(pos + torch.tensor([0.01, 0.0, 0.0]) * (torch.arange(10) > 0)[:, None], feats,
                            nearest, leaves)
        assert not torch.allclose(out, out2)
        q = predictor_from_json(json.loads(json.dumps(cfg.to_json())), p.state_arrays())
        assert isinstance(q, ProxyLeafMLP) and q.config == cfg
        assert torch.equal(q.predict(pos, feats, nearest, leaves)[0], out)

    def test_fit_trains_it_and_encode_refits_a_residual_predictor(self, tiny, tmp_path):
        from proxycodec.formats.container import read_container

        from proxycodec import codec
        from proxycodec.model import SceneModel, weights_path_for
        from proxycodec.proxy import load_fitted_predictor as load_predictor

        out = tmp_path / "pl.ply"
        res = _fit(tiny[0], out, small_config(predictor="proxy-leaf-mlp", recon_loss="l1"))
        meta = read_container(weights_path_for(out)).meta["fit"]
        assert meta["predictor"]["kind"] == "proxy-leaf-mlp" and meta["stage"] == 2
        assert meta["config"]["predictor"] == "proxy-leaf-mlp" and meta["config"]["recon_loss"] == "l1"
        assert load_predictor(weights_path_for(out)) == (None, None)  # the container stores residual ones only
        m = SceneModel.load(out)
        assert torch.equal(m.scene.features, res.model.scene.features)
        r = codec.encode(out, tmp_path / "pl.pxc", distill=False, predictor_iters=5)
        assert r.meta["proxy"]["source"] == "encode"
        assert codec.decode(tmp_path / "pl.pxc").scene.num_anchors == m.scene.num_anchors

    def test_checkpoint_round_trip_in_stage_2(self, tiny, tmp_path):
        from proxycodec.formats.datasets import load_dataset

        from proxycodec.proxy import ProxyLeafMLP
        from proxycodec.train import Trainer

        data = load_dataset(tiny[0])
        cfg = small_config(predictor="proxy-leaf-mlp", iters=10)
        tr = Trainer(data, cfg, "tiny")
        for _ in range(6):
            tr.train_step()
        assert tr.stage == 2 and isinstance(tr.predictor, ProxyLeafMLP)
        tr.save_checkpoint(tmp_path / "c.pxc")
        tr2 = Trainer(data, cfg, "tiny")
        tr2.load_checkpoint(tmp_path / "c.pxc")
        assert isinstance(tr2.predictor, ProxyLeafMLP)
        for a, b in zip(tr.predictor.state_dict().values(), tr2.predictor.state_dict().values()):
            assert torch.equal(a, b)


# ------------------------------------------------------------------------------------------------ gate
@pytest.fixture(scope="class")
def gated(tiny, tmp_path_factory):
    """A gated fit with non-default kappa / eta (one per class that asks for it)."""
    out = tmp_path_factory.mktemp("gated") / "g.ply"
    r = CliRunner().invoke(_cli(), ["fit", str(tiny[0]), "-o", str(out), "--iters", "8", "--init-points", "200",
                                    "--gate-kappa", "6", "--gate-eta", "0.5", "--no-proxies"])
    assert r.exit_code == 0, r.output
    return out


class TestGateSwitches:
    def test_kappa_eta_are_stored_and_rendered_with(self, gated, tmp_path):
        from proxycodec import codec
        from proxycodec.model import SceneModel, render_scene
        from proxycodec.render.project import GateConfig

        m = SceneModel.load(gated)
        assert m.decoder.config.gate == GateConfig(True, 6.0, 0.5)
        assert m.meta["fit"]["config"]["gate_kappa"] == 6.0 and m.meta["fit"]["config"]["gate_eta"] == 0.5
        codec.encode(gated, tmp_path / "g.pxc", distill=False, predictor_iters=2)
        assert codec.decode(tmp_path / "g.pxc").decoder.config.gate == GateConfig(True, 6.0, 0.5)
        cam = m.cameras[0]
        with torch.no_grad():
            r1 = render_scene(m.scene, m.decoder, cam, 0.5)  # the model's own gate
            r2 = render_scene(m.scene, m.decoder, cam, 0.5, gate=GateConfig(True, 4.0, 0.25))
        g1 = dict(zip(r1.projected.index.tolist(), r1.projected.gate.double().tolist()))
        g2 = dict(zip(r2.projected.index.tolist(), r2.projected.gate.double().tolist()))
        common = [i for i in g1 if i in g2 and 0.02 < g1[i] < 0.98 and 0.02 < g2[i] < 0.98]
        assert len(common) > 5
        logit = lambda g: math.log(g / (1 - g))
        for i in common:  # the same coverage A = eta + logit(g) / kappa under both settings
            assert 0.5 + logit(g1[i]) / 6.0 == pytest.approx(0.25 + logit(g2[i]) / 4.0, abs=2e-4)
        assert any(abs(g1[i] - g2[i]) > 0.01 for i in common)

    def test_eval_gate_on_off_differ(self, tiny, tmp_path):
        out = tmp_path / "ng.ply"
        r = CliRunner().invoke(_cli(), ["fit", str(tiny[0]), "-o", str(out), "--iters", "8", "--init-points", "200",
                                        "--no-gate", "--no-proxies"])
        assert r.exit_code == 0, r.output
        reps = {}
        for mode in ("model", "on", "off"):
            r = CliRunner().invoke(_cli(), ["eval", str(out), str(tiny[0]), "-o", str(tmp_path / mode), "--res",
                                            "0.25,1.0", "--views", "1", "--gate", mode])
            assert r.exit_code == 0, r.output
            reps[mode] = json.loads((tmp_path / mode / "eval.json").read_text())
        assert reps["model"]["summary"]["gate"]["enabled"] is False
        assert reps["on"]["summary"]["gate"] == {"mode": "on", "enabled": True, "kappa": 4.0, "eta": 0.25}
        assert reps["off"]["summary"]["psnr_avg"] == reps["model"]["summary"]["psnr_avg"]
        assert reps["on"]["summary"]["psnr_avg"] != reps["off"]["summary"]["psnr_avg"]

    def test_eval_gate_refuses_plain_3dgs(self, tiny, tmp_path):
        from proxycodec.model import apply_gate_mode
        from proxycodec.explicit import ExplicitModel

        assert apply_gate_mode(object(), "model") is None
        with pytest.raises(ProxycodecError, match="plain 3DGS"):
            apply_gate_mode(ExplicitModel.__new__(ExplicitModel), "on")


def test_eval_scores_a_container_at_its_fits_reference_width(tiny, tmp_path):
    """eval without --max-width scores a container at the reference its fit trained at (read from the cameras it
    carries: a container holds no fit record), as it scores the fitted PLY, not at the photos' width;
    --max-width still wins."""
    from proxycodec import codec

    out = tmp_path / "half.ply"
    r = CliRunner().invoke(_cli(), ["fit", str(tiny[0]), "-o", str(out), "--iters", "4", "--init-points", "200",
                                    "--max-width", str(SIZE // 2), "--no-proxies"])
    assert r.exit_code == 0, r.output
    codec.encode(out, tmp_path / "half.pxc", distill=False, predictor_iters=2)
    widths = {}
    for name, scene, extra in (("ply", out, []), ("pxc", tmp_path / "half.pxc", []),
                               ("forced", tmp_path / "half.pxc", ["--max-width", str(SIZE)])):
        r = CliRunner().invoke(_cli(), ["eval", str(scene), str(tiny[0]), "-o", str(tmp_path / name), "--res",
                                        "0.5,1.0", "--views", "1", *extra])
        assert r.exit_code == 0, r.output
        rep = json.loads((tmp_path / name / "eval.json").read_text())
        widths[name] = [d["width"] for d in rep["per_resolution"]]
    assert widths == {"ply": [SIZE // 4, SIZE // 2], "pxc": [SIZE // 4, SIZE // 2], "forced": [SIZE // 2, SIZE]}


def _cli():
    from proxycodec.cli.main import cli

    return cli


# ------------------------------------------------------------------------------------------------ Pareto
def test_pareto_front_on_a_hand_made_set():
    from proxycodec.bench import pareto_front

    pts = [
        {"bytes": 100, "psnr_avg": 20.0},  # 0 front (smallest)
        {"bytes": 200, "psnr_avg": 25.0},  # 1 front
        {"bytes": 250, "psnr_avg": 24.0},  # 2 dominated by 1
        {"bytes": 300, "psnr_avg": 25.0},  # 3 dominated by 1 (equal PSNR, more bytes)
        {"bytes": 400, "psnr_avg": 30.0},  # 4 front
        {"bytes": 400, "psnr_avg": 30.0},  # 5 a duplicate of 4: neither dominates the other
        {"bytes": 50, "psnr_avg": None},  # 6 ignored
        {"bytes": 90, "psnr_avg": 19.0},  # 7 front (fewer bytes than 0)
    ]
    assert pareto_front(pts) == [7, 0, 1, 4, 5]
    assert pareto_front([]) == []
    assert pareto_front([{"t": 3.0, "psnr_avg": 1.0}, {"t": 1.0, "psnr_avg": 2.0}], x="t") == [1]


def test_the_report_states_step_time_and_the_wall_time_only_of_runs_that_ended():
    """A map paused and resumed: a run killed at a pause records no wall time, so the report sums the steps'
    own times (each step once; a fit resumed from its checkpoint with its whole training) and says how many runs its
    wall time leaves out."""
    from proxycodec.bench import markdown_report
    from proxycodec.bench.report import time_summary

    meta = {"runs": [{"wall_seconds": 100.0}, {}, {"wall_seconds": 2500.4}],
            "steps": {"fit:a": {"seconds": 1500.0}, "encode:a": {"seconds": 600.25}, "eval:a": {"seconds": None},
                      # resumed from its checkpoint: this run's 300 s of wall time, 900 s of training in all
                      "fit:b": {"seconds": 300.0, "result": {"resumed": True, "seconds": 900.0}},
                      "fit:c": {"seconds": 300.0, "result": {"seconds": 900.0}}}}
    line = time_summary(meta)
    assert line.startswith("step time 3,300 s in 5 step(s); wall time 2,600 s over the 2 of 3 run(s)")
    assert line.endswith("(1 stopped early: no wall time recorded)")
    assert "stopped" not in time_summary({"runs": [{"wall_seconds": 5.0}], "steps": {}})
    assert line in markdown_report("t", meta, [])


def test_ablations_compare_with_the_row_the_paper_compares_with():
    """The paper's lambda_recon deltas are against its schedule, not against our default (lambda_recon = 0): those
    rows take their delta, sign and noise verdict from the schedule row; the others from our reference."""
    tradeoff = load_benchmark("tradeoff")
    names = {a[0] for a in tradeoff.ABLATIONS}
    assert set(tradeoff.PAPER_BASIS) <= names and set(tradeoff.PAPER_BASIS.values()) <= names
    sched = {"name": tradeoff._SCHEDULE, "psnr_avg": 28.3, "delta": -0.3}
    fixed = {"name": "lambda_recon fixed 0.01", "psnr_avg": 28.35, "delta": -0.25, "paper_delta": 0.006}
    tradeoff._compare_like_the_paper(fixed, sched)
    assert fixed["delta_paper_basis"] == pytest.approx(0.05) and fixed["same_direction_as_paper"] is True
    assert fixed["paper_basis"] == tradeoff._SCHEDULE and fixed["delta"] == -0.25  # vs our reference: kept
    gate = {"name": "gate kappa 5", "psnr_avg": 28.8, "delta": 0.1, "paper_delta": -0.054}
    tradeoff._compare_like_the_paper(gate, None)
    assert gate["delta_paper_basis"] == 0.1 and gate["same_direction_as_paper"] is False
    none = {"name": "x", "psnr_avg": None, "delta": None, "paper_delta": -1.0}
    tradeoff._compare_like_the_paper(none, sched)
    assert none["delta_paper_basis"] is None and none["same_direction_as_paper"] is None
    md = "\n".join(tradeoff.ablation_markdown([{**fixed, "scene": "lego", "width": 200, "iters_planned": 3000,
                                                 "psnr_10": 1.0, "psnr_100": 2.0, "ssim_avg": 0.9,
                                                 "iterations": 3000, "within_noise": True}], {}))
    assert "| -0.250 |" in md and "| +0.050 | yes (within noise) |" in md


def test_every_ablation_changes_something_from_the_reference():
    """An ablation row whose overrides are the defaults is the reference fit again (two rows of the map at 83d5913
    measured nothing, +0.000 dB, after the defaults moved to spread proxies and context 4): each row changes a fit
    setting from FitConfig's default, or renders with another gate mode."""
    import dataclasses

    from proxycodec.train import FitConfig

    tradeoff = load_benchmark("tradeoff")
    defaults = {f.name: f.default for f in dataclasses.fields(FitConfig)}
    for name, overrides, gate_mode, _, _ in tradeoff.ABLATIONS:
        assert set(overrides) <= set(defaults), name
        FitConfig(**overrides)  # a valid configuration
        changed = {k for k, v in overrides.items() if v != defaults[k]}
        assert changed or gate_mode != "model", f"{name}: {overrides} are the defaults"


def test_encode_sweep_plan_centres_on_the_defaults():
    from proxycodec.bench import encode_sweep_plan, knob_id
    from proxycodec.codec import EncodeConfig

    plan = encode_sweep_plan(quick=True)
    assert {n for n, _, _ in plan} == {"proxy_ratio", "leaf_sample", "bits", "zstd_level", "predictor_blocks",
                                       "entropy", "positions", "weights_dtype"}
    for name, _, knobs in plan:
        assert knobs["use_fitted"] is False
        EncodeConfig(**knobs).check()
    ids = {knob_id(k) for _, _, k in plan}
    assert "encode default (refit)" in ids and "encode proxy_ratio=0.1" in ids
    assert {"encode entropy=zstd", "encode entropy=model"} <= ids  # the default is "auto"
    assert "encode positions=delta" in ids  # the default is "octree"
    assert {"encode weights_dtype=q8", "encode weights_dtype=q6"} <= ids  # around the default q7
    bits = [k for n, _, k in plan if n == "bits"]
    assert bits and all(k["learned_steps"] is False for k in bits)  # else inert on a rate-trained scene
    assert "encode learned_steps=False, offset_bits=6" in ids
    with pytest.raises(ProxycodecError, match="unknown sweep"):
        encode_sweep_plan(True, ["nope"])


def test_encode_leaf_sample_is_recorded(tiny, tmp_path):
    from proxycodec import codec

    r = codec.encode(tiny[1], tmp_path / "a.pxc", distill=False, predictor_iters=3, leaf_sample=0.05)
    assert r.meta["training"]["sample_frac"] == 0.05
    with pytest.raises(ProxycodecError, match="leaf sample"):
        codec.encode(tiny[1], tmp_path / "b.pxc", leaf_sample=0.0)


# ------------------------------------------------------------------------------------------------ bench
def _check_outputs(out: Path) -> dict:
    res = json.loads((out / "results.json").read_text())
    for name in ("bench.md", "psnr_vs_bytes.png", "psnr_vs_time.png", "render_time_vs_resolution.png"):
        assert (out / name).stat().st_size > 0, name
    assert res["meta"]["machine"]["cpu_count"] and res["meta"]["versions"]["torch"]
    assert res["runs"][-1]["loadavg_start"] is not None and "loadavg_end" in res["runs"][-1]
    return res


def test_bench_quick_end_to_end_in_process(tiny, tmp_path):
    data, ply = tiny
    out = tmp_path / "b"
    r = CliRunner().invoke(_cli(), ["bench", str(ply), str(data), "--quick", "-o", str(out), "--in-process",
                                    "--views", "1", "--sweeps", "proxy_ratio,zstd_level,positions",
                                    "--predictor-iters", "100",
                                    "--distill-iters", "5"])
    assert r.exit_code == 0, r.output
    res = _check_outputs(out)
    pts = {p["id"]: p for p in res["points"]}
    sweeps = {n for p in res["points"] for n in (p.get("sweeps") or {})}
    assert sweeps == {"proxy_ratio", "zstd_level", "positions"}  # (every sweep's plan: test_encode_sweep_plan_...)
    d = pts["encode default"]
    assert d["default"] and d["bytes"] > 0 and math.isfinite(d["psnr_avg"]) and d["views"] == 1
    assert set(d["render_ms"]) == {f"{0.1 * k:.1f}".rstrip("0").rstrip(".") for k in range(1, 11)}
    assert pts["encode proxy_ratio=0.1"]["bytes"] < pts["encode proxy_ratio=0.6"]["bytes"]
    z3 = pts["encode zstd_level=3"]
    assert z3["quality_from"] in ("encode default", "encode default (refit)") and z3["decode_seconds"] is not None
    assert z3["psnr_avg"] == pts["encode default (refit)"]["psnr_avg"]
    oc = pts["encode positions=delta"]  # lossless: the same decoded scene, so the same evaluation, other bytes
    assert oc["quality_from"] in ("encode default", "encode default (refit)") and oc["bytes"] != z3["bytes"]
    assert oc["psnr_avg"] == pts["encode default (refit)"]["psnr_avg"]
    # ... which holds because they are the same scene: the shared evaluation is earned, not assumed
    from proxycodec import codec
    from proxycodec.bench.runner import safe_name

    pxc = {p.stem: p for p in (out / "work").rglob("*.pxc")}
    ref = codec.decode(pxc[safe_name(z3["quality_from"])]).scene
    for pid in ("encode zstd_level=3", "encode positions=delta"):
        got = codec.decode(pxc[safe_name(pid)]).scene
        for k in ("positions", "features", "offsets", "scalings"):
            assert torch.equal(getattr(got, k), getattr(ref, k)), (pid, k)
    assert any(p["pareto"] for p in res["points"])
    md = (out / "bench.md").read_text()
    assert "### Sweep: proxy_ratio" in md and "Pareto" in md and "Render time per resolution" in md
    # LPIPS beside PSNR/SSIM, and one line saying whether it was computed (and from which weights)
    from proxycodec.perceptual import MIN_SIDE, lpips_status

    ok, note = lpips_status()
    assert "| avg LPIPS |" in md and md.count(note) == 1 and d["lpips_note"] == note
    assert "lpips_avg" in d and (d["lpips_avg"] is None) == (not ok or SIZE < MIN_SIDE)


def test_bench_subprocess_steps_and_resume(tiny, tmp_path, monkeypatch):
    """The real path: every step in its own process (per-step RSS); a second run reuses every step, with the folder
    named relatively too; other code reuses them only with ``any_code``."""
    from proxycodec.bench import run_bench
    from proxycodec.bench import runner as R

    data, ply = tiny
    out = tmp_path / "s"
    logs = []
    run_bench(str(ply), str(data), str(out), quick=True, views=1, sweeps=["zstd_level"], predictor_iters=50, distill_iters=5,
              log=logs.append)
    res = _check_outputs(out)
    steps = res["steps"]
    assert all(s["status"] == "ok" and s["rss_scope"] == "own process" for s in steps.values())
    assert all(s["result"]["peak_rss_mb"] > 10 for s in steps.values())
    assert {s["kind"] for s in steps.values()} == {"encode", "eval"}
    n_logged = len(logs)
    monkeypatch.chdir(tmp_path)  # the same folder, named relatively: the same steps
    run_bench(str(ply), str(data), "s", quick=True, views=1, sweeps=["zstd_level"], predictor_iters=50, distill_iters=5,
              log=logs.append)
    assert len(logs) == n_logged  # nothing ran again
    assert len(json.loads((out / "results.json").read_text())["runs"]) == 2
    monkeypatch.setattr(R, "code_key", lambda: "other code")
    run_bench(str(ply), str(data), str(out), quick=True, views=1, sweeps=["zstd_level"], predictor_iters=50, distill_iters=5,
              any_code=True, log=logs.append)
    assert len(logs) == n_logged  # other code, told to reuse: nothing ran again


def _steps_without_timing(path) -> dict:
    """Each step's record in ``results.json`` without what depends on when and where it ran (times, memory, load)."""
    def strip(v):
        if isinstance(v, dict):
            return {k: strip(x) for k, x in v.items() if not (
                k in ("ms", "host", "ray", "shared_host_with", "rss_scope", "finished") or
                any(w in k for w in ("second", "time", "rss", "load", "_at", "_ms")))}
        if isinstance(v, list):
            return [strip(x) for x in v]
        return v

    return {sid: strip(rec) for sid, rec in json.loads(path.read_text())["steps"].items()}


def test_a_map_run_in_waves_on_ray_records_what_the_runner_records(tiny, tmp_path):
    """``tradeoff.py --ray``: the map's passes collect the steps, a wave runs those whose inputs exist as Ray tasks
    (an evaluation waits for its container), into the same cache; the results equal the runner's, step by step."""
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install -e \".[ray]\")")
    from proxycodec.bench import EvalSpec, Runner, encode_point
    from proxycodec.bench.runner import RaySteps

    data, ply = tiny
    ev = EvalSpec(str(data), None, 1, resolutions=(0.5, 1.0))

    def a_pass(runner):
        evaluated = {}  # zstd levels 3 and 19 store the same arrays: the second point reuses the first's quality
        return [encode_point(runner, "t", f"zstd {z}", ply, {"predictor_iters": 20, "zstd_level": z,
                                                              "distill": False}, ev, evaluated=evaluated)
                for z in (3, 19)]

    seq = Runner(tmp_path / "seq", {}, log=lambda s: None)
    points_seq = seq.run_in_waves(lambda: a_pass(seq))
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        steps = RaySteps(cpus_per_step=1)
        assert steps.info["nodes"] == 1 and steps.cpus_per_step == 1
        logs = []
        par = Runner(tmp_path / "par", {}, log=logs.append, ray=steps)
        points_par = par.run_in_waves(lambda: a_pass(par))
    finally:
        ray.shutdown()
    assert sum("... (Ray)" in s for s in logs) >= 4  # two encodes, then their evaluations, then a decode timing
    a, b = _steps_without_timing(tmp_path / "seq" / "results.json"), _steps_without_timing(tmp_path / "par" /
                                                                                         "results.json")
    for sid in a:  # the same steps, with the same results (paths aside: each run has its folder)
        assert json.dumps(a[sid]).replace("/seq/", "/par/") == json.dumps(b[sid]), sid
    assert set(b) - set(a) <= {"eval:t/zstd 19"}  # a wave may evaluate both before it knows they are identical
    assert [p["psnr_avg"] for p in points_seq] == [p["psnr_avg"] for p in points_par]
    assert [p["bytes"] for p in points_seq] == [p["bytes"] for p in points_par]
    recs = json.loads((tmp_path / "par" / "results.json").read_text())["steps"].values()
    assert all(r["ray"]["cpus_per_step"] == 1 and "shared_host_with" in r for r in recs)


def test_a_step_is_reused_only_when_the_same_code_recorded_it(tmp_path, monkeypatch):
    """Steps are cached by code (the package's sources) and configuration (the step's arguments): the map resumes
    across interruptions, and other code runs them again unless asked to reuse them."""
    from proxycodec.bench import runner as R

    calls = []
    monkeypatch.setattr(R, "run_worker", lambda kind, args: calls.append(args) or {"value": args["x"]})
    key = R.code_key()
    assert len(key) == 16 and key == R.code_key()

    def run(code, **kw):
        monkeypatch.setattr(R, "code_key", lambda: code)
        r = R.Runner(tmp_path, {}, isolate=False, log=lambda s: None, **kw)
        out = [r.step("a", "encode", {"x": 1}), r.step("b", "encode", {"x": 2})]
        r.finish()
        return out

    first = run("c1")
    assert len(calls) == 2 and first[0]["code"] == "c1"
    run("c1")
    assert len(calls) == 2  # same code, same arguments: reused
    run("c2")
    assert len(calls) == 4  # other code: run again
    run("c3", any_code=True)
    assert len(calls) == 4
    monkeypatch.setattr(R, "code_key", lambda: "c2")
    r = R.Runner(tmp_path, {}, isolate=False, log=lambda s: None)
    r.step("a", "encode", {"x": 5})  # other arguments: run again
    assert len(calls) == 5
