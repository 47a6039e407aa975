"""The exported 3DGS PLY opens in a real third-party tool: PlayCanvas splat-transform converts it to SPZ."""

import gzip
import shutil
import struct
import subprocess
import sys

import numpy as np
import pytest

TOOL = "@playcanvas/splat-transform@2.7.1"


def _npx_tool_available() -> str | None:
    if shutil.which("npx") is None:
        return "npx (Node.js) is not installed"
    try:
        r = subprocess.run(["npx", "-y", TOOL, "--help"], capture_output=True, text=True, timeout=240)
    except subprocess.TimeoutExpired:
        return f"npx could not fetch {TOOL} in time (no registry access?)"
    if r.returncode != 0 or "splat-transform" not in r.stdout:
        return f"npx could not run {TOOL} (no registry access?): {r.stderr.strip()[-200:]}"
    return None


def test_decoded_ply_converts_to_spz_with_splat_transform(tmp_path):
    why = _npx_tool_available()
    if why:
        pytest.skip(why)
    from proxycodec import codec
    from proxycodec.formats.inria_ply import read_inria_ply
    from proxycodec.sample import sample_model
    from proxycodec.model import SceneModel

    full = sample_model()
    model = SceneModel(full.scene.subset(np.arange(0, full.scene.num_anchors, 8)), full.decoder, full.cameras)
    codec.encode(model, tmp_path / "s.pxc", distill=False, predictor_iters=20)
    r = subprocess.run([sys.executable, "-c", "from proxycodec.cli.main import main; main()", "decode",
                        str(tmp_path / "s.pxc"), "--res", "0.5", "--view", "0", "-o", str(tmp_path / "r"),
                        "--ply", str(tmp_path / "g.ply")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    n = read_inria_ply(tmp_path / "g.ply").n_gaussians
    assert n > 100
    conv = subprocess.run(["npx", "-y", TOOL, str(tmp_path / "g.ply"), str(tmp_path / "g.spz")],
                          capture_output=True, text=True, timeout=240)
    assert conv.returncode == 0, conv.stdout + conv.stderr
    raw = (tmp_path / "g.spz").read_bytes()
    if raw[:2] == b"\x1f\x8b":  # SPZ up to v3 is gzipped; later versions start with the header itself
        raw = gzip.decompress(raw)
    magic, version, count = struct.unpack_from("<III", raw, 0)
    assert magic == 0x5053474E  # "NGSP"
    assert count == n  # every Gaussian we wrote survived the third-party reader
