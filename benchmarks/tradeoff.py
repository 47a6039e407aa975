"""What accuracy costs in time and bytes: one command for every table and plot.

    python benchmarks/tradeoff.py                       # full: lego (400 px) + bonsai (800 px), ~8 h on 2 cores
    python benchmarks/tradeoff.py --quick               # CI smoke: lego at 160 px, tiny budgets, <= 20 min
    python benchmarks/tradeoff.py --scenes lego --out benchmarks/results/tradeoff --budget-scale 0.5
    python benchmarks/tradeoff.py --ray [ADDRESS]       # the independent steps as Ray tasks (a cluster's width)

Per scene, in one run, each step in its own subprocess (``proxycodec.bench``: per-step peak RSS, results written as
each step finishes, a re-run resumes):

1. fit-budget sweep: ``fit`` under wall-time budgets (the largest is the *main* fit), each encoded with the default
   settings (``proxycodec encode SCENE``: the stage-2 proxies and predictor as fitted) and evaluated;
2. the main fit uncompressed (anchor PLY + weights);
3. baselines at the main budget: plain Scaffold-GS (``fit --no-proxies --no-gate --embedding none --fixed-res
   --voxel-rule spacing --color-init-steps 0 --init-gaussian-scale 1``) uncompressed, and plain 3DGS (``fit
   --explicit``) as an INRIA PLY and as SPZ (``npx @playcanvas/splat-transform``, converted back to PLY to evaluate
   what the SPZ holds; skipped with the reason when npx cannot run it);
4. encode-side sweeps on the main fit, one knob at a time around the defaults, predictor refitted at each point:
   proxy ratio, leaf sample fraction per predictor iteration, quantisation bits (uniform grids of those depths,
   ``learned_steps=False``: on a rate-trained scene encode otherwise quantises on the learned grids and the bit
   knobs change nothing), zstd level, predictor depth, entropy coding, position coding (lossless: encodes that decode
   to the same scene share one evaluation);
4b. the rate-distortion sweep: fits at the main budget with the rate term (``fit --lambda-rate``, ``RATE_LAMBDAS``),
   each encoded with the defaults (entropy model, learned grids) and evaluated: with the main fit (the default
   1e-4) they are the RD curve of the entropy model (issue #17);
4c. the anchor density (bonsai: a scene with SfM points): ``fit --voxel-rule spacing`` and ``extent`` at the main
   budget, each encoded with the defaults, beside the default ``auto`` (the main fit, which picks one of the two by
   its probe's pace): what the finer anchors cost in iterations and bytes, and whether ``auto`` picked the better;
5. the paper's ablations (lego) at a smaller reference width and a fixed number of iterations (``ABLATION``: 200 px,
   3000 iterations; iteration budgets give every fit the same length whatever the machine's load, which a 2-minute
   wall-time budget did not: two seeds of the default differed by 2.2 dB), each evaluated uncompressed (the
   PLY holds the leaves' predicted features) against the default fit of the same settings, next to the paper's
   figure; a second seed of the default measures the run-to-run noise.

Step time on the 2-core machine (benchmarks/README.md, "The map at commit 83d5913"): bonsai 11,705 s, lego
8,837 s without the ablations, the ablations ~8,500 s (17 fits of ~490 s: the default fit trains with the rate
term, ~0.1 s per stage-2 step) and their evaluations: ~8 h from scratch, more than a 3-hour run holds.
``--no-ablations`` or ``--scenes lego`` shorten it; a re-run without ``--fresh`` resumes from the finished steps.
Steps are cached by code and configuration: a step is reused when the same package sources (``runner.code_key``) ran
it with the same arguments, so a map resumed after the code changed re-runs what the change may affect (all of it);
to resume one map across such changes, run it from a worktree at a fixed commit (``git worktree add``), or pass
``--any-code`` to reuse whatever is recorded.

Outputs in ``--out``: ``results.json`` (machine, versions, seed, load averages, every step and point), ``tradeoff.md``
(tables), ``psnr_vs_bytes.png`` (Pareto front marked, default highlighted), ``psnr_vs_time.png``,
``render_time_vs_resolution.png``; ``work/`` holds the fitted scenes and containers, ``logs/`` each step's stderr.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
SEED = 0

# Full mode. Budgets are seconds of training; the last one is the main fit. Views: the first N test views.
SCENES = {
    "lego": {"dataset": SHARED / "nerf_synthetic" / "lego", "max_width": 400, "views": 8, "budgets": [120, 400, 900],
             "test_every": 8},
    "bonsai": {"dataset": SHARED / "mipnerf360" / "bonsai", "max_width": 800, "views": 4, "budgets": [300, 600],
               "test_every": 8, "voxel_rules": ["spacing", "extent"]},
}
QUICK = {"lego": {"max_width": 160, "views": 2, "budgets": [20, 60]}}
# "voxel_rules": fit's fixed anchor densities at the main budget (a scene with SfM points only: without them the
# rule is extent / 128 whatever is asked), each encoded with the defaults, beside the default ``--voxel-rule auto``
# (which picks one of them by the pace of its probe steps): whether it picked the better one at this budget.
# The rate term's weights of the RD sweep (fit --lambda-rate), around the main fit's default (1e-4).
RATE_LAMBDAS = (0.0, 3e-5, 3e-4)
QUICK_RATE_LAMBDAS = (0.0,)
# The ablations' fits: reference width and iterations (each its own fit, the reference included).
ABLATION = {"max_width": 200, "iters": 3000}
QUICK_ABLATION = {"max_width": 100, "iters": 400}
ABLATION_SCENES = ("lego",)

# The paper's ablations: (name, FitConfig overrides, eval gate mode, paper figure, paper delta vs ours in dB on the
# dataset named first, or None). NeRF-Synthetic figures first where the paper has them (lego is NeRF-Synthetic).
ABLATIONS = [
    ("coverage gate off (trained and rendered without)", {"gate": False}, "model",
     "not reported in the sources we hold", None),
    ("coverage gate post hoc (trained without, rendered with)", {"gate": False}, "on",
     "[M]: post-hoc gating costs ~1.3 dB vs joint training (Mip-NeRF360)", -1.3),
    ("resolution embedding additive", {"embedding": "additive"}, "model",
     "[M] Mip-NeRF360 avg: additive 28.036 vs FiLM 28.183", 28.036 - 28.183),
    ("resolution embedding none", {"embedding": "none"}, "model",
     "[M] Mip-NeRF360 avg: none 27.199 vs FiLM 28.183", 27.199 - 28.183),
    ("predictor Proxy&Leaf MLP", {"predictor": "proxy-leaf-mlp"}, "model",
     "[S Table 5] T&T 23.276 vs 24.600; DeepBlending 29.606 vs 29.905", 23.276 - 24.600),
    ("L_recon MSE", {"recon_loss": "mse"}, "model",
     "[S Table 6] NeRF-Syn 31.184 vs 31.056; Mip360 28.009 vs 28.183", 31.184 - 31.056),
    ("L_recon L1", {"recon_loss": "l1"}, "model",
     "[S Table 6] NeRF-Syn 29.931 vs 31.056; Mip360 27.391 vs 28.183", 29.931 - 31.056),
    ("lambda_recon paper schedule (0.1, then 0.01 from 2/3; our default is 0)", {"lambda_recon_fixed": None},
     "model", "[S Table 10] the paper's default", None),
    ("lambda_recon fixed 0.1", {"lambda_recon_fixed": 0.1}, "model",
     "[S Table 10] NeRF-Syn 31.007 vs 31.056; T&T 24.451 vs 24.600", 31.007 - 31.056),
    ("lambda_recon fixed 0.01", {"lambda_recon_fixed": 0.01}, "model",
     "[S Table 10] NeRF-Syn 31.062 vs 31.056; T&T 24.194 vs 24.600", 31.062 - 31.056),
    ("gate kappa 4, eta 0.1", {"gate_eta": 0.1}, "model", "[S Table 11] NeRF-Syn 31.020 vs 31.056", 31.020 - 31.056),
    ("gate kappa 4, eta 0.33", {"gate_eta": 0.33}, "model", "[S Table 11] NeRF-Syn 30.497 vs 31.056",
     30.497 - 31.056),
    ("gate kappa 4, eta 0.5", {"gate_eta": 0.5}, "model", "[S Table 11] NeRF-Syn 29.271 vs 31.056", 29.271 - 31.056),
    ("gate kappa 5, eta 0.25", {"gate_kappa": 5.0}, "model", "[S Table 11] NeRF-Syn 31.002 vs 31.056",
     31.002 - 31.056),
    # the paper's stage-2 settings where ours differ (SPEC section 5: our defaults spread the proxies and show the
    # predictor 4 of them): each row is the paper's setting, its delta what ours buys with the sign turned
    ("proxy selection random (the paper's; ours spreads them)", {"proxy_selection": "random"}, "model",
     "[S 7.3] the paper draws proxies at random only", None),
    ("predictor context 1 proxy (the paper's; ours sees 4)", {"predictor_context": 1}, "model",
     "[S 7.1] the paper's predictor sees the nearest proxy only", None),
]
# Where the paper's delta is against a setting other than our default, the row it is measured against: Table 10
# compares fixed lambda_recon with the paper's schedule, while our default is 0 (SPEC section 5).
_SCHEDULE = "lambda_recon paper schedule (0.1, then 0.01 from 2/3; our default is 0)"
PAPER_BASIS = {"lambda_recon fixed 0.1": _SCHEDULE, "lambda_recon fixed 0.01": _SCHEDULE}
QUICK_ABLATIONS = ("coverage gate off (trained and rendered without)",
                   "coverage gate post hoc (trained without, rendered with)", "L_recon MSE",
                   "predictor Proxy&Leaf MLP")
# Scaffold-GS's own voxel (the SfM points' spacing) whatever the budget: ``auto`` is ours
SCAFFOLD = {"proxies": False, "gate": False, "embedding": "none", "fixed_res": True, "voxel_rule": "spacing",
            "color_init_steps": 0, "init_gaussian_scale": 1.0}


def fit_config(budget: float, seed: int, iters: int | None = None, **overrides) -> dict:
    """A fit of ``budget`` seconds of training, or of ``iters`` iterations when given (``budget`` is then only the
    expected time)."""
    return {"iters": iters, "time_budget": None if iters else float(budget), "seed": seed, "checkpoint_every": 120.0,
            "log_every": 30.0, **overrides}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="CI smoke: lego only, small reference, tiny budgets")
    ap.add_argument("--scenes", default=None, help="comma-separated subset of lego,bonsai [default: both; quick: lego]")
    ap.add_argument("--out", default=None, help="results folder [default: benchmarks/results/tradeoff(_quick)]")
    ap.add_argument("--budget-scale", type=float, default=1.0, help="multiply every fit budget (trial runs)")
    ap.add_argument("--views", type=int, default=None, help="test views per evaluation (overrides the per-scene value)")
    ap.add_argument("--max-width", type=int, default=None, help="100%% reference width (overrides the per-scene value)")
    ap.add_argument("--seed", type=int, default=SEED)
    ap.add_argument("--no-ablations", action="store_true")
    ap.add_argument("--ablation-iters", type=int, default=None, help="iterations per ablation fit [default: "
                    f"{ABLATION['iters']}; quick: {QUICK_ABLATION['iters']}]")
    ap.add_argument("--no-spz", action="store_true", help="skip the SPZ conversion (recorded as skipped)")
    ap.add_argument("--fresh", action="store_true", help="ignore the results of an earlier run in --out")
    ap.add_argument("--any-code", action="store_true",
                    help="reuse steps recorded by other code too (default: only the same package sources)")
    ap.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                    help="run the independent steps as Ray tasks, in waves (same step cache): a local Ray started "
                         "here, or ADDRESS (auto, ray://host:port)")
    ap.add_argument("--ray-cpus-per-step", type=float, default=None,
                    help="CPUs each step reserves on Ray [default: a whole node's, so timed steps never share cores]")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(REPO))
    from proxycodec import bench
    from proxycodec.bench import Runner
    from proxycodec.threads import set_threads

    set_threads()  # $PROXYCODEC_THREADS, else the usable cores; the step workers inherit the count

    names = [s.strip() for s in args.scenes.split(",")] if args.scenes else (["lego"] if args.quick else list(SCENES))
    for n in names:
        if n not in SCENES or (args.quick and n not in QUICK):
            ap.error(f"unknown scene {n!r} for this mode")
    specs = {}
    for n in names:
        sp = dict(SCENES[n], **(QUICK.get(n, {}) if args.quick else {}))
        sp["budgets"] = [round(b * args.budget_scale, 3) for b in sp["budgets"]]
        if args.views:
            sp["views"] = args.views
        if args.max_width:
            sp["max_width"] = args.max_width
        if not Path(sp["dataset"]).is_dir():
            ap.error(f"dataset for {n} not found: {sp['dataset']} (see ../shared/data/README.md)")
        specs[n] = sp
    ablations = [] if args.no_ablations else [a for a in ABLATIONS if not args.quick or a[0] in QUICK_ABLATIONS]
    ab_scenes = [n for n in names if n in ABLATION_SCENES]
    # A second seed of the ablation reference measures run-to-run noise (full mode only).
    noise_seeds = [] if args.quick else [args.seed + 1]
    ab_spec = dict(QUICK_ABLATION if args.quick else ABLATION)
    if args.ablation_iters:
        ab_spec["iters"] = args.ablation_iters
    n_rate = len(QUICK_RATE_LAMBDAS if args.quick else RATE_LAMBDAS)
    est = sum(sum(sp["budgets"]) + (2 + n_rate + len(sp.get("voxel_rules", []))) * sp["budgets"][-1]
              for sp in specs.values())
    # a rough rate of 20 iterations/s at 200 px, scaling with the pixel count
    ab_fit_s = ab_spec["iters"] / 20.0 * (ab_spec["max_width"] / 200.0) ** 2
    est += sum(ab_fit_s * (1 + len({tuple(sorted(a[1].items())) for a in ablations}) + len(noise_seeds))
               for n in ab_scenes)
    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / ("tradeoff_quick" if args.quick
                                                                             else "tradeoff")
    meta = {"kind": "proxycodec.tradeoff", "quick": args.quick, "seed": args.seed, "machine": bench.machine_info(),
            "versions": bench.versions(), "budget_scale": args.budget_scale,
            "scenes": {n: {"dataset": str(sp["dataset"]), "reference width": sp["max_width"],
                           "test views evaluated": sp["views"], "fit budgets (s)": sp["budgets"],
                           "main fit budget (s)": sp["budgets"][-1]} for n, sp in specs.items()},
            "ablation_fits": {n: {"reference width": ab_spec["max_width"], "iterations": ab_spec["iters"]}
                              for n in ab_scenes},
            "fit_seconds_planned": est}
    ray = None
    if args.ray:
        try:
            from proxycodec.bench.runner import RaySteps
        except ImportError:  # pragma: no cover
            ap.error("--ray needs Ray: pip install -e \".[ray]\"")
        try:
            ray = RaySteps(None if args.ray == "local" else args.ray, args.ray_cpus_per_step)
        except ImportError:
            ap.error("--ray needs Ray: pip install -e \".[ray]\"")
        meta["ray"] = ray.info
    runner = Runner(out, meta, fresh=args.fresh, ray=ray, any_code=args.any_code)
    runner.log(f"trade-off benchmark -> {out}: scenes {names}, ~{est / 60:.0f} min of training planned "
               f"(plus encodes and evaluations)" + (f"; on Ray: {ray.info}" if ray else ""))
    t0 = time.time()
    points, ablation_rows = runner.run_in_waves(lambda: map_pass(runner, args, specs, ablations, ab_scenes,
                                                                  noise_seeds, ab_spec, ab_fit_s))
    md_ab = ablation_markdown(ablation_rows, meta)
    paths = bench.write_report(runner, "Trade-off benchmark" + (" — quick" if args.quick else ""),
                               points, extra_sections=md_ab, extra_json={"ablations": ablation_rows})
    print(Path(paths["markdown"]).read_text())
    print(f"done in {time.time() - t0:.0f} s; wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


def map_pass(runner, args, specs, ablations, ab_scenes, noise_seeds, ab_spec, ab_fit_s) -> tuple[list, list]:
    """One pass over the map: every step in order (each run, or taken from the cache); -> (points, ablation rows).
    With Ray, ``Runner.run_in_waves`` repeats it, running the steps each pass asks for in parallel."""
    from proxycodec.bench import EvalSpec, encode_point, eval_step, make_point, run_encode_sweeps

    points: list[dict] = []
    ablation_rows: list[dict] = []
    for n, sp in specs.items():
        ev = EvalSpec(str(sp["dataset"]), sp["max_width"], sp["views"], sp["test_every"])
        data_args = {"dataset": str(sp["dataset"]), "max_width": sp["max_width"], "test_every": sp["test_every"]}
        wd = runner.work / n
        evaluated: dict = {}

        def fit(tag, budget, seed=args.seed, data=data_args, iters=None, **over):
            # the file is named by the tag: an evaluation step is keyed by its arguments, the file's path among them
            ply = wd / f"fit_{tag}.ply"
            rec = runner.step(f"fit:{n}/{tag}", "fit", {**data, "out": str(ply),
                                                        "config": fit_config(budget, seed, iters, **over)},
                              outputs=[ply], timeout=3 * budget + 900)
            return ply, rec

        # 1. fit budgets (+ default encode); the last is the main fit, whose default encode is the sweeps' default
        fits = {}
        for b in sp["budgets"]:
            fits[b] = fit(f"budget={b:g}", b)
        main_b = sp["budgets"][-1]
        main_ply, main_fit = fits[main_b]
        for b in sp["budgets"][:-1]:
            ply, rec = fits[b]
            p = encode_point(runner, n, f"ours, fit {b:g} s, default encode", ply, {}, ev, fit=rec,
                             evaluated={}, group="fit budget", default=False, sweeps={"fit_budget": f"{b:g} s"})
            points.append(p)
        # 2. the main fit uncompressed
        e = eval_step(runner, f"eval:{n}/main uncompressed", main_ply, ev)
        points.append(make_point(n, f"ours uncompressed (PLY + weights), fit {main_b:g} s", "anchor-ply",
                                 fit=main_fit, ev=e, bytes_=_res_bytes(main_fit), group="uncompressed"))
        # 3. baselines at the main budget
        sc_ply, sc_fit = fit(f"scaffold budget={main_b:g}", main_b, **SCAFFOLD)
        e = eval_step(runner, f"eval:{n}/scaffold", sc_ply, ev)
        points.append(make_point(n, f"Scaffold-GS-style, uncompressed, fit {main_b:g} s", "anchor-ply", fit=sc_fit,
                                 ev=e, bytes_=_res_bytes(sc_fit), group="baseline"))
        gs_ply = wd / f"explicit_{main_b:g}.ply"
        gs_fit = runner.step(f"fit:{n}/3dgs budget={main_b:g}", "explicit",
                             {**data_args, "out": str(gs_ply),
                              "config": {"iters": None, "time_budget": float(main_b), "seed": args.seed,
                                         "log_every": 30.0}},
                             outputs=[gs_ply], timeout=3 * main_b + 900)
        e = eval_step(runner, f"eval:{n}/3dgs ply", gs_ply, ev)
        points.append(make_point(n, f"3DGS (INRIA PLY), fit {main_b:g} s", "inria-ply", fit=gs_fit, ev=e,
                                 bytes_=_res_bytes(gs_fit), group="baseline"))
        spz, back = wd / f"explicit_{main_b:g}.spz", wd / f"explicit_{main_b:g}_from_spz.ply"
        if args.no_spz:
            conv = {"status": "skipped", "result": {"skipped": "--no-spz"}}
        elif gs_fit.get("status") == "ok":
            conv = runner.step(f"spz:{n}", "spz", {"ply": str(gs_ply), "out": str(spz), "back": str(back)},
                               outputs=[spz, back], timeout=1800)
        else:
            conv = {"status": "skipped", "result": {"skipped": "no 3DGS PLY"}}
        e = eval_step(runner, f"eval:{n}/3dgs spz", back, ev) if conv.get("status") == "ok" else None
        points.append(make_point(n, f"3DGS -> SPZ (splat-transform), fit {main_b:g} s", "spz", fit=gs_fit,
                                 enc=conv, ev=e, group="baseline"))
        # The fits of 4b and 4c run before the encode sweeps (4): wall-time fits need the machine alone, and a map
        # paused within the sweeps' hours resumes with encodes only (bonsai: ~300 s each, ~20 of them)
        # 4b. the RD sweep: the rate term at the main budget, each fit encoded with the defaults
        for lam in (QUICK_RATE_LAMBDAS if args.quick else RATE_LAMBDAS):
            ply, rec = fit(f"rate={lam:g} budget={main_b:g}", main_b, lambda_rate=lam)
            points.append(encode_point(runner, n, f"ours, fit {main_b:g} s, --lambda-rate {lam:g}, default encode",
                                       ply, {}, ev, fit=rec, evaluated=evaluated, group="rate", default=False,
                                       sweeps={"lambda_rate": f"{lam:g}"}))
        # 4c. the anchor density: fit's other voxel rules at the main budget, each encoded with the defaults
        for rule in sp.get("voxel_rules", []):
            ply, rec = fit(f"voxel_rule={rule} budget={main_b:g}", main_b, voxel_rule=rule)
            points.append(encode_point(runner, n, f"ours, fit {main_b:g} s, --voxel-rule {rule}, default encode",
                                       ply, {}, ev, fit=rec, evaluated=evaluated, group="anchor density",
                                       default=False, sweeps={"voxel_rule": rule}))
        # 4. encode sweeps on the main fit (its as-fitted default encode is the scene's default point)
        sw = run_encode_sweeps(runner, n, main_ply, ev, quick=args.quick, fit=main_fit, evaluated=evaluated)
        for p in sw:
            if p["id"] == "encode default":
                p["id"] = f"ours, fit {main_b:g} s, default encode"
                p["sweeps"]["fit_budget"] = f"{main_b:g} s"
        points += sw
        # 5. ablations: fixed iterations at the ablation width, each against the default fit of the same settings
        if n in ab_scenes and ablations:
            ab_w, ab_it = ab_spec["max_width"], ab_spec["iters"]
            ab_ev = EvalSpec(str(sp["dataset"]), ab_w, sp["views"], sp["test_every"])
            ab_data = {**data_args, "max_width": ab_w}

            def ab_fit(tag, seed=args.seed, **over):
                return fit(f"ablation {tag} {ab_w}px {ab_it}it", ab_fit_s, seed, ab_data, ab_it, **over)

            ref_ply, ref_fit = ab_fit("reference")
            ref = _res(eval_step(runner, f"eval:{n}/ablation reference {ab_w}px", ref_ply, ab_ev))
            rows = [{"name": f"reference (defaults, seed {args.seed})", "psnr_avg": ref.get("psnr_avg"),
                     "ssim_avg": ref.get("ssim_avg"), "psnr_10": ref.get("psnr_10"), "psnr_100": ref.get("psnr_100"),
                     "iterations": _res(ref_fit).get("iterations"), "delta": 0.0}]
            for s in noise_seeds:
                ply, rec = ab_fit(f"reference seed={s}", seed=s)
                r = _res(eval_step(runner, f"eval:{n}/ablation reference seed={s} {ab_w}px", ply, ab_ev))
                rows.append(_ablation_row(f"reference (defaults, seed {s}): run-to-run noise", r, ref, rec, None,
                                          "same settings, another seed", {}))
                rows[-1]["noise_row"] = True
            for name, over, gate, paper, paper_delta in ablations:
                tag = ",".join(f"{k}={v}" for k, v in sorted(over.items()))
                ply, rec = ab_fit(tag, **over)
                r = _res(eval_step(runner, f"eval:{n}/ablation {tag} gate={gate} {ab_w}px", ply, ab_ev, gate=gate))
                rows.append(_ablation_row(name, r, ref, rec, paper_delta, paper, {**over, "eval_gate": gate}))
            noise = [abs(r["delta"]) for r in rows if r.get("noise_row") and r.get("delta") is not None]
            by_name = {r["name"]: r for r in rows}
            for r in rows:
                r["scene"], r["width"], r["iters_planned"] = n, ab_w, ab_it
                _compare_like_the_paper(r, by_name.get(PAPER_BASIS.get(r["name"], "")))
                d = r.get("delta_paper_basis")
                if noise and d is not None and not r.get("noise_row") and r is not rows[0]:
                    r["within_noise"] = abs(d) <= max(noise)
            ablation_rows += rows
        if not runner.collecting:
            runner.save({"points": points, "ablations": ablation_rows})  # partial results after each scene
    return points, ablation_rows


def _res(rec):
    return (rec or {}).get("result", {}) if rec and rec.get("status") == "ok" else {}


def _res_bytes(rec):
    return _res(rec).get("bytes")


def _ablation_row(name, r, ref, fit_rec, paper_delta, paper, settings) -> dict:
    d = None if r.get("psnr_avg") is None or ref.get("psnr_avg") is None else r["psnr_avg"] - ref["psnr_avg"]
    return {"name": name, "settings": settings, "psnr_avg": r.get("psnr_avg"), "ssim_avg": r.get("ssim_avg"),
            "psnr_10": r.get("psnr_10"), "psnr_100": r.get("psnr_100"), "iterations": _res(fit_rec).get("iterations"),
            "delta": d, "paper": paper, "paper_delta": paper_delta,
            "error": fit_rec.get("error") if fit_rec and fit_rec.get("status") != "ok" else None}


def _compare_like_the_paper(r: dict, basis: dict | None) -> None:
    """The row's delta on the paper's basis (``basis``: the row the paper's figure is relative to; None: our
    reference) and whether it has the paper's sign."""
    d = r.get("delta")
    if basis is not None:
        d = None if r.get("psnr_avg") is None or basis.get("psnr_avg") is None else r["psnr_avg"] - basis["psnr_avg"]
        r["paper_basis"] = basis["name"]
    r["delta_paper_basis"] = d
    pd = r.get("paper_delta")
    r["same_direction_as_paper"] = None if d is None or pd is None or pd == 0 else (d > 0) == (pd > 0)


def ablation_markdown(rows: list[dict], meta: dict) -> list[str]:
    if not rows:
        return []
    f = lambda x, s=".3f": "n/a" if x is None else format(x, s)  # noqa: E731
    out = ["## Ablations (the paper's, on our data)", "",
           "Each ablation is a fit of the fixed number of iterations below, at the reference width below, with one "
           "setting changed, evaluated uncompressed (anchor PLY + weights; the PLY holds the leaves' predicted "
           "features) on the same views as the reference: the default fit of the same settings. Iteration budgets "
           "give every fit the same length whatever the machine's load, and the same bytes on a re-run; the "
           "reference's second seed shows how much one seed's draw (initialisation, views, resolutions) moves it. "
           "Paper deltas "
           "are on other data and GPU-length training (30k iterations). 'Δ like the paper' is measured against "
           "the row the paper's figure is relative to (its λ_recon rows: the paper's schedule, not our default "
           "λ_recon = 0); 'same sign' compares its direction with the paper's, and says 'within noise' where "
           "its size is no larger than the second seed's Δ.", ""]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        rs = [r for r in rows if r["scene"] == scene]
        out += [f"### {scene}, {rs[0]['width']} px reference, {rs[0]['iters_planned']} iterations per fit", "",
                "| ablation | avg PSNR | Δ vs reference | PSNR 10% | PSNR 100% | avg SSIM | iters | paper | "
                "paper Δ | Δ like the paper | same sign |", "|---|---:|---:|---:|---:|---:|---:|---|---:|---:|:-:|"]
        for r in rs:
            same = {True: "yes", False: "**no**", None: ""}[r.get("same_direction_as_paper")]
            if r.get("within_noise"):
                same += " (within noise)"
            name = r["name"] + (f" — {r['error']}" if r.get("error") else "")
            out.append(f"| {name} | {f(r['psnr_avg'])} | {f(r['delta'], '+.3f')} | {f(r['psnr_10'])} | "
                       f"{f(r['psnr_100'])} | {f(r['ssim_avg'], '.4f')} | {f(r['iterations'], 'd')} | "
                       f"{r.get('paper', '')} | {f(r.get('paper_delta'), '+.3f')} | "
                       f"{f(r.get('delta_paper_basis'), '+.3f')} | {same} |")
        out.append("")
    return out


if __name__ == "__main__":
    sys.exit(main())
