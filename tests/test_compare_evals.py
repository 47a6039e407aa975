"""``benchmarks/compare_evals.py``: eval reports side by side, margins over a baseline, refusals of mismatched ones."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import load_benchmark

XI = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0]


@pytest.fixture(scope="module")
def ce():
    return load_benchmark("compare_evals")


def _report(path: Path, psnr: list[float], xi=XI, views=(0, 8)) -> Path:
    per = [{"xi": x, "width": int(800 * x), "height": 10, "psnr": p, "ssim": 0.5, "seconds": 0.1, "gaussians": 1,
            "lpips": None} for x, p in zip(xi, psnr)]
    path.write_text(json.dumps({"scene": "s", "views": list(views), "summary": {}, "per_resolution": per}))
    return path


def test_margins_table_json_and_plot(ce, tmp_path, capsys):
    a = _report(tmp_path / "a.json", [30.0 - i * 0.5 for i in range(10)])
    b = _report(tmp_path / "b.json", [20.0 + i for i in range(10)])
    out = tmp_path / "out"
    assert ce.main([f"ours={a}", f"3dgs={b}", "--baseline", "3dgs", "--paper", "mipnerf360", "--bytes", "ours=1234",
                    "--out", str(out)]) == 0
    doc = json.loads((out / "compare.json").read_text())
    ours = doc["reports"][0]
    m = [30.0 - i * 0.5 - (20.0 + i) for i in range(10)]
    assert ours["margin"]["per_resolution"] == pytest.approx(m)
    assert ours["margin"]["min"] == pytest.approx(min(m)) and ours["margin"]["mean"] == pytest.approx(sum(m) / 10)
    assert "margin" not in doc["reports"][1] and doc["bytes"] == {"ours": 1234}
    assert ours["psnr_mean"] == pytest.approx(sum(30.0 - i * 0.5 for i in range(10)) / 10)
    md = (out / "compare.md").read_text()
    assert "| ours - 3dgs |" in md and "1,234" in md and "paper: 3D-GS" in md and md == capsys.readouterr().out
    assert (out / "psnr_vs_resolution.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_refuses_mismatched_reports(ce, tmp_path):
    a = _report(tmp_path / "a.json", [25.0] * 10)
    out = str(tmp_path / "o")
    with pytest.raises(SystemExit, match="resolutions"):
        ce.main([f"a={a}", f"b={_report(tmp_path / 'b.json', [25.0] * 3, xi=XI[:3])}", "--out", out])
    with pytest.raises(SystemExit, match="test views"):
        ce.main([f"a={a}", f"c={_report(tmp_path / 'c.json', [25.0] * 10, views=(0,))}", "--out", out])
    with pytest.raises(SystemExit, match="none of the labels"):
        ce.main([f"a={a}", "--baseline", "zz", "--out", out])
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(SystemExit, match="bad.json: not a proxycodec eval report"):
        ce.main([f"a={bad}", "--out", out])
    with pytest.raises(SystemExit, match="expected LABEL=EVAL_JSON"):
        ce.main([str(a), "--out", out])
