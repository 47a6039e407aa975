"""As run 2026-11-29 (paths of that machine). Re-encode the 2400-s bonsai conversion's anchor scene with encode options; score each against the source."""
import json, os, subprocess, sys, time
from pathlib import Path
from proxycodec.bench.steps import run_worker
W = Path("/work/runs/convtime/t2400/work/bonsai")
OUT = Path("/work/runs/reenc")
configs = {k: v.split() for k, v in (a.split("=", 1) for a in sys.argv[1:])}
res = json.loads((OUT / "results.json").read_text()) if (OUT / "results.json").exists() else {}
for name, opts in configs.items():
    if name in res:
        continue
    pxc = OUT / f"{name}.pxc"
    t0 = time.perf_counter()
    r = subprocess.run(["proxycodec", "encode", os.environ.get("SRC", str(W / "converted_anchors.ply")), "-o", str(pxc), *opts],
                       capture_output=True, text=True)
    (OUT / f"{name}.log").write_text(r.stdout + r.stderr)
    if r.returncode:
        print(name, "failed", r.stderr[-500:]); continue
    enc_s = time.perf_counter() - t0
    vs = run_worker("vs_source", {"model": str(pxc), "source": str(W / "point_cloud.ply"),
                                  "cameras": str(W / "cameras.json"), "background": [0, 0, 0], "views": 4})
    res[name] = {"opts": opts, "bytes": pxc.stat().st_size, "encode_s": enc_s, "psnr": vs["psnr_avg"],
                 "per_res": vs["per_resolution"]}
    print(name, res[name]["bytes"], round(4886712 / res[name]["bytes"], 3), round(vs["psnr_avg"], 3), flush=True)
    (OUT / "results.json").write_text(json.dumps(res, indent=1))
