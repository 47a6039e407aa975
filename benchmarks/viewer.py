"""``proxycodec view`` on a real container: start time, frame time, and a headless-Chromium screenshot against our
own render of the camera the browser reports.

    python benchmarks/viewer.py lego.pxc [--size 800x600] [--res 1,0.5,0.25] [--starts 3]

Start time: ``proxycodec view CONTAINER`` in a fresh process, from the command's start to its ``serving`` line
(median of ``--starts``). Then, in this process: ``start_viewer``; Chromium (Debian's ``chromium``) opens the page at
``--size`` with ``?fixedDpr=1`` and the viewport's screenshot (the canvas alone) is compared, per slider resolution,
with (a) the viewer's frame for the camera the browser reports and (b) the torch path's render of that camera
(``codec.decode``), both upscaled nearest as the viewer shows them. Outputs in ``--out`` (default
``benchmarks/results/viewer``): ``viewer.json``, ``viewer.md`` and a screenshot per resolution.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def psnr8(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)


def cli_start(container: str, n: int) -> list[float]:
    from proxycodec.bench.browser import free_port

    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        p = subprocess.Popen([sys.executable, "-m", "proxycodec.cli", "view", container, "--port", str(free_port())],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            line = p.stdout.readline()
            out.append(time.perf_counter() - t0)
            if not line.startswith("serving"):
                raise RuntimeError(f"view did not start: {line}")
        finally:
            p.terminate()
            p.communicate(timeout=60)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("container")
    ap.add_argument("--size", default="800x600")
    ap.add_argument("--res", default="1,0.5,0.25")
    ap.add_argument("--starts", type=int, default=3)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec import codec
    from proxycodec.bench import machine_info, versions
    from proxycodec.bench.browser import ONLY_THE_CANVAS, DevTools, chromium, free_port, wait_for
    from proxycodec.fileio import write_bytes_atomic
    from proxycodec.model import image_to_uint8
    from proxycodec.viewer import start_viewer, upscale_nearest

    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / "viewer"
    out.mkdir(parents=True, exist_ok=True)
    W, H = (int(x) for x in args.size.split("x"))
    starts = cli_start(args.container, args.starts)
    print(f"proxycodec view: serving {statistics.median(starts):.2f} s after the command starts (median of "
          f"{len(starts)}: {', '.join(f'{s:.2f}' for s in starts)})", flush=True)
    exe = chromium()
    if exe is None:
        print("no Chromium (Debian: apt-get install chromium): no screenshot")
        return 1
    torch_model = codec.decode(args.container)
    v = start_viewer(args.container, port=free_port(), log=None)
    rows = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            browser = DevTools(exe, Path(tmp) / "profile", W, H)
            try:
                browser.call("Page.navigate", url=v.url + "/?fixedDpr=1")
                if not v.wait_frames(1, 120):
                    raise RuntimeError("the viewer sent no frame")
                cam0 = torch_model.cameras[0] if torch_model.cameras else v.initial_camera
                wait_for(lambda: np.abs(v.last_frame.camera.world_to_camera - cam0.world_to_camera).max() < 1e-6,
                         60, "a frame of the first camera")
                browser.evaluate(ONLY_THE_CANVAS)
                for xi in (float(x) for x in args.res.split(",")):
                    n = v.frames_sent if v.xi != xi else -1  # at the slider's value already: the last frame
                    v._gui["res"].value = xi  # the slider, as a user moves it
                    wait_for(lambda: v.frames_sent > n and v.last_frame.xi == xi, 60, f"a frame at {xi:g}")
                    frame = v.last_frame
                    ours = upscale_nearest(image_to_uint8(torch_model.render(frame.camera, xi).image), W, H)
                    prev = [None]

                    def settled():
                        raw, img = browser.screenshot()
                        same, prev[0] = prev[0] is not None and np.array_equal(prev[0], img), img
                        return (raw, img) if same and img.shape == frame.display.shape and \
                            psnr8(img, frame.display) > 30 else None

                    raw, img = wait_for(settled, 60, "the screenshot to settle", step=0.3)
                    shot = out / f"screenshot_{xi:g}.png"
                    write_bytes_atomic(shot, raw)
                    row = {"xi": xi, "render_size": [frame.stats["width"], frame.stats["height"]],
                           "render_ms": frame.stats["render_ms"],
                           "psnr_vs_viewer_frame": psnr8(img, frame.display),
                           "max_abs_diff_vs_viewer_frame": int(np.abs(img.astype(int) - frame.display).max()),
                           "psnr_vs_torch_render": psnr8(img, ours), "screenshot": shot.name,
                           "anchors_kept": frame.stats.get("anchors_kept"),
                           "gaussians_kept": frame.stats.get("gaussians_projected")}
                    rows.append(row)
                    print(f"{xi:g}: {row['render_size'][0]}x{row['render_size'][1]} in {row['render_ms']:.0f} ms; "
                          f"screenshot vs the viewer's frame {row['psnr_vs_viewer_frame']:.2f} dB (max |diff| "
                          f"{row['max_abs_diff_vs_viewer_frame']}), vs the torch render "
                          f"{row['psnr_vs_torch_render']:.2f} dB", flush=True)
            finally:
                browser.close()
    finally:
        v.stop()
    meta = {"container": args.container, "viewport": [W, H], "start_s": starts, "start_s_median":
            statistics.median(starts), "start_viewer_s": v.start_seconds, "machine": machine_info(),
            "versions": versions(), "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "date": time.strftime("%Y-%m-%d")}
    write_bytes_atomic(out / "viewer.json", json.dumps({"meta": meta, "rows": rows}, indent=1).encode())
    md = [f"# proxycodec view on {Path(args.container).name}", "",
          f"Serving {meta['start_s_median']:.2f} s after `proxycodec view` starts (median of {len(starts)}); "
          f"viewport {W}x{H} in headless Chromium.", "",
          "| slider | render size | render ms | screenshot vs viewer frame (dB) | max diff | vs torch render (dB) |",
          "|---:|---|---:|---:|---:|---:|"]
    md += [f"| {r['xi']:g} | {r['render_size'][0]}x{r['render_size'][1]} | {r['render_ms']:.0f} | "
           f"{r['psnr_vs_viewer_frame']:.2f} | {r['max_abs_diff_vs_viewer_frame']} | {r['psnr_vs_torch_render']:.2f} |"
           for r in rows]
    write_bytes_atomic(out / "viewer.md", ("\n".join(md) + "\n").encode())
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
