"""The H200 equal-time table (benchmarks/README.md, "Bonsai at equal time on an H200, 140 s"): the GPU evals of
stage d (ours, PLY + weights) and g (plain 3DGS) from gpu_dgn.json, and the CPU evals of the two containers
(eval_d_container_cpu.json, eval_x_container_cpu.json), side by side with compare_evals.py. Run from the repository
root: python benchmarks/results/gpu_h200_abe4079/equal_time/table.py"""
import json
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
RES = HERE.parent
stages = json.loads((RES / "gpu_dgn.json").read_text())["stages"]


def report(per: list[tuple[float, float, float]]) -> dict:
    """An eval-report-shaped dict (xi, psnr, ssim per size); views None: the GPU evals keep no view list."""
    return {"views": None, "per_resolution": [{"xi": x, "psnr": p, "ssim": s} for x, p, s in per]}


tmp = Path(tempfile.mkdtemp())
args = []
for label, st in (("ours", "d"), ("3dgs", "g")):
    per = stages[st]["eval"]["per_resolution"]
    (tmp / f"{label}.json").write_text(json.dumps(report([(float(k), v["psnr"], v["ssim"]) for k, v in per.items()])))
    args.append(f"{label}={tmp / f'{label}.json'}")
for label, name in (("ours_pxc", "eval_d_container_cpu.json"), ("ours_extent_pxc", "eval_x_container_cpu.json")):
    per = json.loads((RES / name).read_text())["per_resolution"]
    (tmp / f"{label}.json").write_text(json.dumps(report([(d["xi"], d["psnr"], d["ssim"]) for d in per])))
    args.append(f"{label}={tmp / f'{label}.json'}")
x_bytes = json.loads((RES / "x_encode.json").read_text())["file_bytes"]
cmd = [sys.executable, str(RES.parent.parent / "compare_evals.py"), *args, "--baseline", "3dgs", "--paper",
       "mipnerf360", "--bytes", f"ours_pxc={stages['n']['encode']['bytes']}", "--bytes",
       f"ours_extent_pxc={x_bytes}", "--bytes", f"3dgs={stages['g']['spz_bytes']}", "--out", str(HERE)]
sys.exit(subprocess.run(cmd, check=False).returncode)
