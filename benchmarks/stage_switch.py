"""What the stage switch costs, and which ways into stage 2 win it back: one stage-1 state, several ways in.

    python benchmarks/stage_switch.py [DATASET] [--max-width 800] [--iters 2000] [--after 400] [--views 12]
        [--variants default,warm3000,norate,nolr,stage1,ramp40] [--out DIR]

A fit (``FitConfig`` defaults, extent density, seed 0, ``--iters`` iterations: stage 2 from half of them) runs
stage 1 once and keeps its checkpoint (``DIR/stage1.ckpt.pxc``). Each variant then starts from that checkpoint with
one setting changed, enters stage 2 and trains ``--after`` iterations; the held-out PSNR (the first ``--views`` test
views at 10 / 30 / 60 / 100%, against the anti-aliased photos) is taken before the switch, right after it (with the
leaves predicted; with the rate term's rounding alone, leaves kept) and at the end. Variants:

- ``default``: the defaults; ``stage1``: no stage 2 (``proxies`` off: what the same iterations give without it);
- ``warm3000``: 3,000 L_recon-only predictor iterations at the switch instead of 300;
- ``norate``: no rate term (``lambda_rate`` 0); ``nolr``: the decoder's learning rates not restarted;
- ``rampF``: the leaves' rendered features pass from their own to the predicted values over F% of stage 2
  (``FitConfig.leaf_ramp``); ``rampF_warm3000``: both.

Every variant sees the same views and sizes (the run's random stream comes from the checkpoint). Writes
``stage_switch.json`` (machine, versions, seed, every score, the training PSNR per 100 iterations, peak RSS) as each
variant ends (a re-run skips the variants it holds) and prints the table. DATASET defaults to bonsai in
``../shared/data`` (skipped with a reason when absent).
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data" / "mipnerf360" / "bonsai"
RES = [0.1, 0.3, 0.6, 1.0]
SEED = 0
VARIANTS = {
    "default": {}, "stage1": {"proxies": False}, "warm3000": {"predictor_warmup": 3000},
    "warm0": {"predictor_warmup": 0},
    "norate": {"lambda_rate": 0.0}, "nolr": {"decoder_lr_stage2": False},
    "ramp20": {"leaf_ramp": 0.2}, "ramp40": {"leaf_ramp": 0.4},
    "ramp40_warm3000": {"leaf_ramp": 0.4, "predictor_warmup": 3000},
}
#: the settings a variant may change from the checkpoint's (loaded under the checkpoint's own, then set)
CHANGED = sorted({k for v in VARIANTS.values() for k in v})


@torch.no_grad()
def score(tr, views, rounded: bool = True, predicted: bool = True) -> dict:
    """Held-out PSNR at ``RES`` of the trainer's scene as it would be saved now: the rate term's rounding
    (``rounded``), the leaves' predicted features (``predicted``, stage 2)."""
    from proxycodec.metrics import psnr
    from proxycodec.model import render_scene

    a = tr.anchors
    f, o, s = a.features.detach().clone(), a.offsets.detach().clone(), a.scalings.detach()
    if tr.rate is not None and rounded:
        f, o, s = tr.rate.rounded(f, o, s)
    if tr.stage >= 2 and predicted and tr.leaves.numel():
        tr.predictor.eval()
        f[tr.leaves] = tr.predictor.predict(a.positions, f.clone(), tr.nearest, tr.leaves, None, tr.encodings)[0]
        tr.predictor.train()
    scene = replace(a.export(f, {}, o), scalings=s)
    tr.decoder.eval()
    out = {str(xi): float(np.mean([psnr(render_scene(scene, tr.decoder, tr.data.cameras[i], xi, background=tr.bg)
                                        .image.clamp(0, 1).numpy(), tr.images.get(i, xi).numpy()) for i in views]))
           for xi in RES}
    tr.decoder.train()
    out["mean"] = float(np.mean([out[str(xi)] for xi in RES]))
    return out


def load_variant(tr, ckpt: Path, cfg) -> None:
    """``tr.load_checkpoint`` under the checkpoint's own settings, then the variant's (``CHANGED``)."""
    from proxycodec.formats.container import read_container
    from proxycodec.train import FitConfig

    saved = FitConfig.from_json(read_container(ckpt).meta["config"])
    tr.cfg = replace(cfg, **{k: getattr(saved, k) for k in CHANGED})
    tr.load_checkpoint(ckpt)
    tr.cfg = cfg


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", nargs="?", default=str(DEFAULT_DATA))
    ap.add_argument("--max-width", type=int, default=800)
    ap.add_argument("--iters", type=int, default=2000)
    ap.add_argument("--after", type=int, default=400, help="stage-2 iterations per variant")
    ap.add_argument("--views", type=int, default=12)
    ap.add_argument("--variants", default="default,stage1,warm3000,norate,nolr,ramp40")
    ap.add_argument("--out", default=str(HERE / "results" / "stage_switch"))
    a = ap.parse_args(argv)
    if not Path(a.dataset).is_dir():
        print(f"skipped: {a.dataset}: no dataset (../shared/data absent?)", file=sys.stderr)
        return 0
    names = a.variants.split(",")
    if unknown := [n for n in names if n not in VARIANTS]:
        ap.error(f"unknown variants {unknown}; choose from {', '.join(VARIANTS)}")
    from proxycodec.bench.runner import machine_info, versions
    from proxycodec.formats.datasets import load_dataset
    from proxycodec.train import FitConfig, Trainer

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "stage_switch.json"
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    data = load_dataset(a.dataset, max_width=a.max_width)
    base = FitConfig(max_width=a.max_width, iters=a.iters, seed=SEED, voxel_rule="extent")
    views = data.test_indices[:a.views]
    res = json.loads(path.read_text()) if path.exists() else {}
    res.update({"machine": machine_info(), "versions": versions(), "seed": SEED, "dataset": a.dataset,
                "max_width": a.max_width, "iters": a.iters, "after": a.after, "views": len(views), "resolutions": RES})
    ckpt = out / "stage1.ckpt.pxc"
    if not ckpt.exists():
        tr = Trainer(data, base, a.dataset, log)
        tr.color_init()
        t0 = time.perf_counter()
        while tr.progress() < base.stage2_start:
            tr.train_step()
            if tr.iteration % 100 == 0:
                log(f"stage 1: iteration {tr.iteration}, {time.perf_counter() - t0:.0f} s")
        tr.save_checkpoint(ckpt)
    variants = res.setdefault("variants", {})
    for name in names:
        if name in variants:
            continue
        cfg = replace(base, **VARIANTS[name])
        tr = Trainer(data, cfg, a.dataset, log)
        load_variant(tr, ckpt, cfg)
        r = {"settings": VARIANTS[name], "before": score(tr, views)}
        t0 = time.perf_counter()
        if cfg.proxies:
            tr.enter_stage2()
        r["switch_s"] = time.perf_counter() - t0
        r["after_switch"] = score(tr, views)
        r["after_switch_rounding_only"] = score(tr, views, predicted=False)
        ps, t0 = [], time.perf_counter()
        for k in range(a.after):
            ps.append(float(10 * np.log10(1 / max(float(tr.train_step()["mse"]), 1e-10))))
            if (k + 1) % 100 == 0:
                log(f"{name}: iteration {tr.iteration}, training PSNR {np.mean(ps[-100:]):.2f} (last 100), "
                    f"{time.perf_counter() - t0:.0f} s")
        r["train_psnr_per_100"] = [round(float(np.mean(ps[k:k + 100])), 3) for k in range(0, len(ps), 100)]
        r["seconds"] = time.perf_counter() - t0
        r["end"] = score(tr, views)
        log(f"{name}: before {r['before']['mean']:.2f}, after the switch {r['after_switch']['mean']:.2f}, "
            f"after {a.after} iterations {r['end']['mean']:.2f} dB")
        variants[name] = r
        res["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        path.write_text(json.dumps(res, indent=1))
    print(f"| variant | before | after the switch | rounding only | after {a.after} | "
          + " | ".join(f"{int(x * 100)}%" for x in RES) + " | s |")
    print("|---|" + "---:|" * (5 + len(RES)))
    for name, r in variants.items():
        print(f"| {name} | {r['before']['mean']:.2f} | {r['after_switch']['mean']:.2f} | "
              f"{r['after_switch_rounding_only']['mean']:.2f} | **{r['end']['mean']:.2f}** | "
              + " | ".join(f"{r['end'][str(x)]:.2f}" for x in RES) + f" | {r['seconds']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
