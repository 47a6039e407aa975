"""How new anchors start, on bonsai: 400-iteration fits (seed 0, 800 px, extent density) from Scaffold-GS's start,
with the SfM colours, and with smaller Gaussians, each scored on 12 held-out views at 10 / 30 / 50 / 100%
(benchmarks/README.md, "Measurement log", 2026-11-29, "How anchors start"). As run, each alone on the machine:

    python benchmarks/results/bonsai800/how_anchors_start/run.py OUT TAG [FIELD=VALUE ...]

    TAG scaffold   color_init_steps=0 init_gaussian_scale=1.0
    TAG colors     init_gaussian_scale=1.0
    TAG colors_03  init_gaussian_scale=0.3
    TAG colors_01  init_gaussian_scale=0.1
    TAG default    (the defaults since: colours and the ratio rule, 0.329 here)

Writes OUT/TAG.ply (+ weights), OUT/TAG.log (the fit's log) and OUT/TAG_eval/ (``proxycodec eval``).
"""
import ast
import subprocess
import sys
from pathlib import Path

from proxycodec.formats.datasets import load_dataset
from proxycodec.train import FitConfig, fit

out, tag = Path(sys.argv[1]), sys.argv[2]
kw = {k: ast.literal_eval(v) for k, v in (a.split("=", 1) for a in sys.argv[3:])}
data_dir = str(Path(__file__).resolve().parents[5] / "shared/data/mipnerf360/bonsai")
out.mkdir(parents=True, exist_ok=True)
cfg = FitConfig(iters=400, seed=0, max_width=800, **kw)
with open(out / f"{tag}.log", "w") as f:
    fit(load_dataset(data_dir, max_width=800), out / f"{tag}.ply", cfg, dataset_root=data_dir,
        log=lambda s: print(s, file=f, flush=True))
subprocess.run(["proxycodec", "eval", str(out / f"{tag}.ply"), data_dir, "--views", "12", "--res", "0.1,0.3,0.5,1.0",
                "-o", str(out / f"{tag}_eval")], check=True, stdout=subprocess.DEVNULL)
print(tag, (out / f"{tag}_eval/eval.md").read_text().split("**")[1])
