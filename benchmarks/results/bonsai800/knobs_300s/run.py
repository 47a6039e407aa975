"""One 300-s bonsai fit at 800 px with one FitConfig field changed (benchmarks/README.md, "Measurement log",
2026-11-29, "Short fits on bonsai"). As run, one at a time, alone on the machine:

    KNOB=offset python run.py base 1 300        # the defaults (voxel rule extent, as auto takes at this length)
    KNOB=offset python run.py x5 5 300          # lr_offset x 5 (Scaffold-GS's offset rate x its cameras_extent)
    KNOB=feature python run.py f4 4 300         # lr_feature x 4
    KNOB=antialiased python run.py aa 0 300     # = proxycodec fit --antialiased
    KNOB=warmup python run.py w1500 1500 300    # = --predictor-warmup 1500
    KNOB=declr python run.py declr 0 300        # = --no-decoder-lr-restart
    proxycodec eval TAG.ply ../shared/data/mipnerf360/bonsai --views 12 --res 0.1,...,1.0 -o eval_TAG
"""
import os
import sys
from dataclasses import replace

from proxycodec.formats.datasets import load_dataset
from proxycodec.train import FitConfig, fit

tag, mult, budget = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
seed = int(sys.argv[4]) if len(sys.argv) > 4 else 0
D = os.environ.get("DATA", "../shared/data/mipnerf360/bonsai")
cfg = FitConfig(seed=seed, max_width=800, time_budget=budget, iters=None, voxel_rule="extent")
kind = os.environ.get("KNOB", "offset")
if kind == "offset":
    cfg = replace(cfg, lr_offset=tuple(x * mult for x in cfg.lr_offset))
elif kind == "feature":
    cfg = replace(cfg, lr_feature=cfg.lr_feature * mult)
elif kind == "antialiased":
    cfg = replace(cfg, antialiased=True)
elif kind == "warmup":
    cfg = replace(cfg, predictor_warmup=int(mult))
elif kind == "declr":
    cfg = replace(cfg, decoder_lr_stage2=False)
data = load_dataset(D, max_width=800)
res = fit(data, f"{tag}.ply", cfg, dataset_root=D)
print("done", res.iterations, res.model.scene.num_anchors)
