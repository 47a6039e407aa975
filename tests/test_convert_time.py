"""``benchmarks/convert_time.py``: rows from ``convert.py`` results, the trend per doubling of the training time, the
runs it starts and the ones it does not repeat."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from conftest import load_benchmark

XI = [round(0.1 * k, 1) for k in range(1, 11)]


@pytest.fixture(scope="module")
def ct():
    return load_benchmark("convert_time")


def _results(path: Path, train_s: float, avg: float, *, complete: bool = True) -> Path:
    """A ``convert.py`` results.json with the fields convert_time reads: per-resolution PSNRs whose mean is ``avg``."""
    per = [{"xi": x, "psnr": avg + 0.5 - (x - 0.1) / 0.9, "ssim": 0.9} for x in XI]  # symmetric about avg
    conv = {"bytes": 500_000, "seconds": train_s + 100, "anchors": 23_000, "peak_rss_mb": 3000.0,
            "convert": {"iterations": int(3 * train_s), "seconds": {"train": train_s}}}
    steps = {"s/convert + encode": {"status": "ok", "result": conv},
             "s/spz": {"status": "ok", "result": {"bytes": 4_800_000}},
             "s/vs source: proxycodec (converted)": {"status": "ok", "result": {"psnr_avg": avg,
                                                                                 "per_resolution": per}},
             "s/vs photos: proxycodec (converted)": {"status": "ok" if complete else "failed",
                                                     "result": {"psnr_avg": 20.0}}}
    meta = {"seed": 0, "machine": {"cpu_count": 2, "cpu_model": "test"}, "versions": {"torch": "x"}}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"steps": steps, "meta": meta}))
    return path


def test_trend_is_the_least_squares_line_on_log2_seconds(ct):
    rows = [{"train_s": t, "psnr_source_avg": 27.0 + 0.5 * math.log2(t / 600)} for t in (600, 1200, 2400)]
    tr = ct.trend(rows, 30.0)
    assert tr["db_per_doubling"] == pytest.approx(0.5, abs=1e-12)
    assert tr["residuals_db"] == pytest.approx([0, 0, 0], abs=1e-12)
    assert tr["seconds_to_bar"] == pytest.approx(600 * 2**6, rel=1e-9)  # 3 dB at 0.5 per doubling
    # no gain with time: no time reaches the bar; one point: no line
    flat = [{"train_s": t, "psnr_source_avg": 27.0} for t in (600, 1200)]
    assert ct.trend(flat, 30.0)["seconds_to_bar"] is None
    assert ct.trend(rows[:1], 30.0) is None


def test_collects_finished_runs_and_starts_only_the_missing_one(ct, tmp_path, monkeypatch):
    out = tmp_path / "sweep"
    _results(out / "t600" / "results.json", 600.0, 27.5)
    _results(out / "t1200" / "results.json", 1200.0, 28.0)
    _results(out / "t2400" / "results.json", 2400.0, 28.5, complete=False)  # its photos step failed: run again
    started = []

    def fake_run(cmd, check):
        started.append(cmd)
        _results(out / "t2400" / "results.json", 2400.0, 28.5)

    monkeypatch.setattr(ct.subprocess, "run", fake_run)
    assert ct.main(["--input", "s=in.ply", "--max-width", "800", "--budgets", "1200,600,2400",
                    "--out", str(out)]) == 0
    assert len(started) == 1
    cmd = started[0]
    assert cmd[cmd.index("--input") + 1] == "s=in.ply" and cmd[cmd.index("--out") + 1] == str(out / "t2400")
    assert "time_budget=2400" in cmd and "iters=null" in cmd and cmd[cmd.index("--max-width") + 1] == "800"

    doc = json.loads((out / "convert_time.json").read_text())
    rows = doc["rows"]
    assert [r["budget_s"] for r in rows] == [600, 1200, 2400]  # sorted by time
    assert rows[0]["spz_ratio"] == pytest.approx(9.6) and rows[1]["iterations"] == 3600
    assert rows[2]["psnr_source_10"] == pytest.approx(29.0) and rows[2]["psnr_source_100"] == pytest.approx(28.0)
    assert doc["trend"]["db_per_doubling"] == pytest.approx(0.5)
    assert doc["trend"]["seconds_to_bar"] == pytest.approx(2400 * 2**3)
    md = (out / "convert_time.md").read_text()
    assert "**+0.50 dB per doubling**" in md and "| 2400 | 7,200 |" in md
    assert (out / "psnr_vs_time.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # everything present: nothing runs again
    started.clear()
    assert ct.main(["--input", "s=in.ply", "--max-width", "800", "--budgets", "600,1200,2400",
                    "--out", str(out)]) == 0
    assert started == []


def test_input_must_name_the_scene(ct, tmp_path):
    with pytest.raises(SystemExit):
        ct.main(["--input", "in.ply", "--max-width", "800", "--out", str(tmp_path)])
