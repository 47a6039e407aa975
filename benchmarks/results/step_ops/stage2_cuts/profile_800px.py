"""torch.profiler over 8 stage-2 training steps of a bonsai fit at 800 px on the CPU (1 thread), after 3 warm-up steps
of stage 2 (``FitConfig(iters=40)``: stage 2 from iteration 20). Prints the operations by self CPU time. Run it with
the commit to measure installed (or on PYTHONPATH): ``python profile_800px.py > profile_800px.txt``."""
from pathlib import Path

from torch.profiler import ProfilerActivity, profile

from proxycodec.formats.datasets import load_dataset
from proxycodec.threads import set_threads
from proxycodec.train import FitConfig, Trainer

BONSAI = Path(__file__).resolve().parents[5] / "shared" / "data" / "mipnerf360" / "bonsai"
set_threads(1)
t = Trainer(load_dataset(str(BONSAI), max_width=800), FitConfig(iters=40, seed=0))
while t.stage < 2:
    t.train_step()
for _ in range(3):
    t.train_step()
with profile(activities=[ProfilerActivity.CPU]) as p:
    for _ in range(8):
        t.train_step()
print(p.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
