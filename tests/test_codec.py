"""The scene codec (proxycodec.codec) and its CLI: exactness, determinism, modes, stats, PLY export."""

from __future__ import annotations

import json
from dataclasses import replace
import subprocess
import sys

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from proxycodec import codec
from proxycodec.camera import orbit_cameras
from proxycodec.cli.main import cli
from proxycodec.decoder import DecoderConfig, GaussianDecoder
from proxycodec.errors import ProxycodecError
from proxycodec.formats.container import ContainerError, read_container, write_container
from proxycodec.sections import read_scene_container
from proxycodec.model import SceneModel
from proxycodec.scene import AnchorScene

FAST = dict(distill=False, predictor_iters=15, predictor_hidden=16, predictor_blocks=1, zstd_level=3)
VOXEL = 0.05


def tiny_model(n=300, seed=0, on_grid=True, rule="f64") -> SceneModel:
    rng = np.random.default_rng(seed)
    cells = np.stack(np.meshgrid(np.arange(12), np.arange(12), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    cells = cells[rng.choice(len(cells), n, replace=False)] - np.array([6, 6, 0])
    if rule == "f64":
        pos = (cells * VOXEL).astype(np.float32)
    else:  # Scaffold-GS: float32 integer times float32 voxel
        pos = cells.astype(np.float32) * np.float32(VOXEL)
    if not on_grid:
        pos = pos + rng.uniform(-0.01, 0.01, pos.shape).astype(np.float32)
    freq = rng.normal(size=(32, 3)) * 2.0
    feats = np.sin(pos.astype(np.float64) @ freq.T + rng.uniform(0, 6.28, 32)).astype(np.float32)
    offs = rng.uniform(-0.5, 0.5, (n, 10, 3)).astype(np.float32)
    scal = (np.log(VOXEL) + rng.normal(0, 0.1, (n, 6))).astype(np.float32)
    scene = AnchorScene(torch.from_numpy(pos), torch.from_numpy(feats), torch.from_numpy(offs),
                        torch.from_numpy(scal), VOXEL, {"name": "tiny"}).validate()
    torch.manual_seed(seed)
    dec = GaussianDecoder(DecoderConfig(scene_center=(0.0, 0.0, 0.1), scene_radius=0.6)).eval()
    cams = orbit_cameras((0.0, 0.0, 0.1), 1.5, 2, width=32, height=24)
    return SceneModel(scene, dec, cams, (1.0, 1.0, 1.0))


def _arrays(model: SceneModel) -> dict[str, np.ndarray]:
    s = model.scene
    out = {k: getattr(s, k).numpy() for k in ("positions", "features", "offsets", "scalings")}
    out.update({f"decoder/{k}": v for k, v in model.decoder.state_arrays().items()})
    return out


def _assert_same(a: SceneModel, b: SceneModel) -> None:
    aa, bb = _arrays(a), _arrays(b)
    assert aa.keys() == bb.keys()
    for k in aa:
        assert aa[k].dtype == bb[k].dtype and aa[k].tobytes() == bb[k].tobytes(), k


def _match(orig: np.ndarray, decoded: np.ndarray) -> np.ndarray:
    """Index into ``orig`` of every decoded anchor (positions are unique)."""
    lookup = {p.tobytes(): i for i, p in enumerate(orig)}
    return np.array([lookup[p.tobytes()] for p in decoded])


@pytest.fixture(scope="module")
def encoded(tmp_path_factory):
    model = tiny_model()
    path = tmp_path_factory.mktemp("codec") / "tiny.pxc"
    report = codec.encode(model, path, **FAST)
    return model, path, report


class TestExactness:
    def test_decode_reproduces_the_reported_model_bit_exactly(self, encoded):
        _, path, report = encoded
        _assert_same(codec.decode(path), report.model)

    def test_positions_exact_and_stored_arrays_on_their_quantisation_lattice(self, encoded):
        model, path, report = encoded
        dec = codec.decode(path)
        meta = report.meta
        assert meta["positions"]["mode"] == "grid"
        orig_pos = model.scene.positions.numpy()
        idx = _match(orig_pos, dec.scene.positions.numpy())  # every decoded position is an original, exactly
        assert sorted(idx.tolist()) == list(range(model.scene.num_anchors))
        mask = dec.scene.metadata["proxy_mask"]
        for name, rows, q in (("scalings", slice(None), meta["quant"]["scalings"]),
                              ("features", mask, meta["quant"]["features"]),
                              ("offsets", slice(None), meta["quant"]["offsets"])):
            d = getattr(dec.scene, name).numpy()[rows].reshape(-1 if name != "features" else int(mask.sum()), len(q["scale"]))
            o = getattr(model.scene, name).numpy()[idx][rows].reshape(d.shape)
            off, sc = np.array(q["offset"]), np.array(q["scale"])
            k = np.rint((d.astype(np.float64) - off) / np.where(sc > 0, sc, 1))
            # d is exactly float32(offset + k * scale), and within half a step of the original
            assert np.array_equal(d, (off + k * sc).astype(np.float32))
            if name == "offsets" and "offsets_dead" in meta:  # never-drawn Gaussians: the level nearest 0
                live = np.repeat(codec._live_slots(dec, report.meta["offsets_dead"]["threshold"]), 3, axis=1)
                zero = np.clip(np.rint(-off / np.where(sc > 0, sc, 1)), 0, 255)
                assert np.array_equal(k[~live], np.broadcast_to(zero, k.shape)[~live])
                d, o = d[live], o[live]
                sc = np.broadcast_to(sc, live.shape)[live]
            assert np.all(np.abs(d - o) <= sc / 2 + 1e-6)

    def test_never_drawn_gaussians_lose_their_offsets_and_nothing_else(self, encoded, tmp_path):
        model, keep_path, keep = encoded
        assert "offsets_dead" not in keep.meta  # opt-in
        report = codec.encode(model, tmp_path / "drop.pxc", drop_dead_offsets=True, **FAST)
        dead = report.meta["offsets_dead"]
        assert 0 < dead["slots"] < dead["of"] == model.scene.num_anchors * 10
        assert keep.file_bytes > report.file_bytes
        self.test_positions_exact_and_stored_arrays_on_their_quantisation_lattice((model, report.path, report))
        a, b = codec.decode(report.path), keep.model
        assert not np.array_equal(a.scene.offsets.numpy(), b.scene.offsets.numpy())
        for cam in model.cameras:  # the cameras the liveness was judged from: identical images
            for xi in (0.1, 0.5, 1.0, 2.0):
                ia, ib = a.render(cam, xi).image, b.render(cam, xi).image
                assert torch.equal(ia, ib), (xi,)

    def test_leaves_are_regenerated_not_stored(self, encoded):
        model, path, report = encoded
        c = read_container(path)
        assert c.arrays["proxy/features"].shape == (32, report.proxies)
        assert not any("leaf" in n for n in c.arrays)
        dec = codec.decode(path)
        mask = dec.scene.metadata["proxy_mask"]
        assert (~mask).sum() == report.leaves > 0

    def test_weights_are_packed_and_scene_format_1_stays_readable(self, encoded, tmp_path):
        """Scene formats 2-6 pack the ~50 weight tensors into a few sections per network (the default, octree
        positions, writes format 6); a format-1 file (one section per tensor, no layout) decodes to the same model
        in both decoders."""
        from proxycodec import lite
        from test_entropy import stored_digest

        model, default_path, report = encoded
        names = [s["name"] for s in report.sections]
        assert report.meta["scene_format"] == 6 and report.meta["features"] == ["octree"]
        assert sorted(n for n in names if n.split("/")[0] in ("decoder", "predictor")) == [
            "decoder/packed.f2", "decoder/packed.f4", "decoder/packed.i1",
            "predictor/packed.f2", "predictor/packed.f4", "predictor/packed.i1"]
        path = tmp_path / "delta.pxc"  # format 1 had delta positions only
        assert codec.encode(model, path, **FAST, positions="delta").meta["scene_format"] == 2
        assert stored_digest(path) == stored_digest(default_path)  # the same scene and symbols
        c = read_scene_container(path)
        old = tmp_path / "v1.pxc"
        write_container(old, {k: v for k, v in c.meta.items() if k != "weights_layout"} | {"scene_format": 1},
                        c.arrays)
        assert old.stat().st_size > path.stat().st_size + 2000  # the table entries packing saves
        a, b = codec.decode(path), codec.decode(old)
        for (k, x), (_, y) in zip(a.decoder.state_dict().items(), b.decoder.state_dict().items()):
            assert torch.equal(x, y), k
        assert torch.equal(a.scene.features, b.scene.features) and torch.equal(a.scene.offsets, b.scene.offsets)
        la, lb = lite.decode(path), lite.decode(old)
        assert np.array_equal(la.features, lb.features)

    def test_fresh_process_decodes_bit_exactly(self, encoded, tmp_path):
        _, path, report = encoded
        out = tmp_path / "dec.npz"
        code = ("import numpy as np, sys; from proxycodec import codec; m = codec.decode(sys.argv[1]); s = m.scene; "
                "np.savez(sys.argv[2], positions=s.positions.numpy(), features=s.features.numpy(), "
                "offsets=s.offsets.numpy(), scalings=s.scalings.numpy(), "
                "**{'decoder/' + k: v for k, v in m.decoder.state_arrays().items()})")
        subprocess.run([sys.executable, "-c", code, str(path), str(out)], check=True, timeout=120)
        got = dict(np.load(out))
        want = _arrays(report.model)
        assert got.keys() == want.keys()
        for k in want:
            assert got[k].tobytes() == want[k].tobytes(), k

    def test_scaffold_float32_grid_rule_and_off_grid_fallback(self, tmp_path):
        m = tiny_model(120, rule="f32")
        r = codec.encode(m, tmp_path / "a.pxc", **FAST)
        assert r.meta["positions"]["mode"] == "grid"
        _match(m.scene.positions.numpy(), codec.decode(tmp_path / "a.pxc").scene.positions.numpy())
        m = tiny_model(120, on_grid=False)
        r = codec.encode(m, tmp_path / "b.pxc", **FAST)
        assert r.meta["positions"]["mode"] == "float32"
        dec = codec.decode(tmp_path / "b.pxc")
        _match(m.scene.positions.numpy(), dec.scene.positions.numpy())
        _assert_same(dec, r.model)

    def test_lossless_bits_and_predicted_offsets(self, tmp_path):
        m = tiny_model(150)
        r = codec.encode(m, tmp_path / "a.pxc", feature_bits=32, offset_bits=32, scaling_bits=32,
                         weights_dtype="f32", predict_offsets=True, **FAST)
        dec = codec.decode(tmp_path / "a.pxc")
        _assert_same(dec, r.model)
        idx = _match(m.scene.positions.numpy(), dec.scene.positions.numpy())
        mask = dec.scene.metadata["proxy_mask"]
        assert np.array_equal(dec.scene.features.numpy()[mask], m.scene.features.numpy()[idx][mask])
        assert np.array_equal(dec.scene.scalings.numpy(), m.scene.scalings.numpy()[idx])
        assert np.array_equal(dec.scene.offsets.numpy()[mask], m.scene.offsets.numpy()[idx][mask])
        assert "proxy/offsets" in read_container(tmp_path / "a.pxc").arrays
        assert r.meta["offsets"] == "predicted"
        for k, v in m.decoder.state_arrays().items():
            assert np.array_equal(dec.decoder.state_arrays()[k], v)

    def test_decoded_arrays_are_row_major_like_a_loaded_ply(self, encoded):
        """The sections are channel-major; a decoded scene must not keep transposed views (every render gathers
        anchors by row: strided rows cost bonsai +30 ms per view)."""
        from proxycodec import lite

        _, path, _ = encoded
        s = codec.decode(path).scene
        for k in ("positions", "features", "offsets", "scalings"):
            assert getattr(s, k).is_contiguous(), k
        ls = lite.decode(path)
        for k in ("positions", "features", "offsets", "scalings"):
            assert getattr(ls, k).flags.c_contiguous, k

    def test_decoded_model_renders(self, encoded):
        _, path, _ = encoded
        r = codec.render(path, 0.5, backend="reference")
        assert len(r) == 2 and r[0].image.shape == (12, 16, 3) and torch.isfinite(r[0].image).all()


class TestDeterminism:
    def test_same_input_and_seed_same_bytes(self, tmp_path):
        m = tiny_model(200)
        codec.encode(m, tmp_path / "a.pxc", seed=5, **FAST)
        codec.encode(m, tmp_path / "b.pxc", seed=5, **FAST)
        codec.encode(m, tmp_path / "c.pxc", seed=6, **FAST)
        a, b, c = ((tmp_path / f"{x}.pxc").read_bytes() for x in "abc")
        assert a == b
        assert a != c

    def test_input_order_does_not_matter_for_the_stored_anchors(self, tmp_path):
        m = tiny_model(200)
        perm = torch.from_numpy(np.random.default_rng(0).permutation(200))
        shuffled = SceneModel(m.scene.subset(perm), m.decoder, m.cameras, m.background)
        codec.encode(m, tmp_path / "a.pxc", **FAST)
        codec.encode(shuffled, tmp_path / "b.pxc", **FAST)
        a, b = read_container(tmp_path / "a.pxc"), read_container(tmp_path / "b.pxc")
        for k in ("anchors/octree", "anchors/octree_p", "anchors/proxy_mask", "anchors/scalings", "anchors/offsets",
                  "proxy/features"):
            assert np.array_equal(a.arrays[k], b.arrays[k]), k


class TestFittedPredictor:
    def test_stage2_predictor_and_mask_from_the_weights_file_are_used_as_is(self, tmp_path):
        from proxycodec.model import weights_path_for
        from proxycodec.proxy import PredictorConfig, ResidualPredictor, select_proxies

        m = tiny_model(120)
        ply, w = m.save(tmp_path / "s.ply")
        mask = select_proxies(m.scene.positions, 0.2, 0.4, seed=11)
        torch.manual_seed(3)
        pred = ResidualPredictor(PredictorConfig(hidden=16, n_blocks=1, dist_ref=VOXEL))
        for p in pred.parameters():
            torch.nn.init.normal_(p, std=0.05)
        c = read_container(w)
        meta = {**c.meta, "fit": {"predictor": pred.config.to_json()}}
        arrays = {**c.arrays, **{f"predictor/{k}": v for k, v in pred.state_arrays().items()},
                  "proxy_mask": mask.astype(np.uint8)}
        write_container(weights_path_for(ply), meta, arrays)
        r = codec.encode(ply, tmp_path / "s.pxc", **{**FAST, "weights_dtype": "f16"})
        assert r.meta["proxy"]["source"] == "fit" and r.training.iters == 0
        dec = codec.decode(tmp_path / "s.pxc")
        idx = _match(m.scene.positions.numpy(), dec.scene.positions.numpy())
        assert np.array_equal(dec.scene.metadata["proxy_mask"], mask[idx])
        got = ResidualPredictor.from_arrays(
            PredictorConfig.from_json(r.meta["predictor"]),
            {k[10:]: v for k, v in read_scene_container(tmp_path / "s.pxc").arrays.items() if k.startswith("predictor/")})
        for k, v in pred.state_arrays().items():
            assert np.array_equal(got.state_arrays()[k], v.astype(np.float16).astype(np.float32)), k
        r2 = codec.encode(ply, tmp_path / "t.pxc", use_fitted=False, **FAST)
        assert r2.meta["proxy"]["source"] == "encode"

    @pytest.mark.parametrize("ties", ["grid", "position", "index"])
    def test_decoded_leaves_are_the_fitted_scene_s_leaves(self, tmp_path, ties):
        """A fit writes its leaves as its predictor predicts them in the trainer's anchor order; the container
        regenerates them in Morton order. With every attribute stored in float32 they must agree: on a voxel grid
        many proxies are equidistant from a leaf, and under the "index" rule (files written before "position")
        their order followed the storage order, so ~10% of the leaves came out with other neighbours (lego: the
        container 0.29 dB below its own PLY)."""
        from proxycodec.model import weights_path_for
        from proxycodec.proxy import PredictorConfig, ResidualPredictor, nearest_proxies, select_proxies

        m = tiny_model(300)
        perm = torch.from_numpy(np.random.default_rng(4).permutation(300))  # a trainer's order, not Morton's
        m = SceneModel(m.scene.subset(perm), m.decoder, m.cameras, m.background)
        mask = select_proxies(m.scene.positions, 0.2, 0.3, seed=1)
        torch.manual_seed(2)
        pred = ResidualPredictor(PredictorConfig(hidden=16, n_blocks=1, dist_ref=VOXEL, context=4, ties=ties))
        for p in pred.parameters():
            torch.nn.init.normal_(p, std=0.1)
        s = m.scene
        leaves = torch.from_numpy(np.flatnonzero(~mask))
        near = torch.from_numpy(nearest_proxies(s.positions, mask, 4, ties, VOXEL))
        with torch.no_grad():  # what fit's result writes: the leaves as predicted, in its own anchor order
            feats = s.features.clone()
            feats[leaves] = pred.predict(s.positions, s.features, near, leaves)[0]
        fitted = SceneModel(replace(s, features=feats), m.decoder, m.cameras, m.background)
        ply, w = fitted.save(tmp_path / "s.ply")
        c = read_container(w)
        write_container(weights_path_for(ply), {**c.meta, "fit": {"predictor": pred.config.to_json()}},
                        {**c.arrays, **{f"predictor/{k}": v for k, v in pred.state_arrays().items()},
                         "proxy_mask": mask.astype(np.uint8)})
        r = codec.encode(ply, tmp_path / "s.pxc", **{**FAST, "feature_bits": 32, "offset_bits": 32,
                                                      "scaling_bits": 32, "weights_dtype": "f32"})
        assert r.meta["predictor"]["ties"] == ties
        dec = codec.decode(tmp_path / "s.pxc")
        idx = _match(s.positions.numpy(), dec.scene.positions.numpy())
        err = np.abs(dec.scene.features.numpy() - feats.numpy()[idx]).max(1)
        if ties != "index":
            assert err.max() < 1e-5
        else:  # the old rule: the storage orders disagree on some leaves (why "position" exists)
            assert (err > 1e-3).sum() > 0.02 * len(leaves)


def test_spread_proxy_selection_reaches_the_container(tmp_path):
    """encode --proxy-selection spread: the container's proxies are select_proxies(..., "spread") of its anchors
    (same count per cell as random, other anchors), and a decoder needs nothing to know which was used."""
    from proxycodec.proxy import select_proxies
    from proxycodec.sections import stored_anchors

    m = tiny_model(300)
    got = {}
    for method in ("random", "spread"):
        r = codec.encode(m, tmp_path / f"{method}.pxc", proxy_selection=method, cell_size=0.2, **FAST)
        c = codec.load(r.path)
        a = stored_anchors(c.meta, c.sections, ProxycodecError)
        assert np.array_equal(a.proxy_mask, select_proxies(a.positions, 0.2, 0.3, 0, method))
        assert np.isfinite(codec.decode(r.path).scene.features.numpy()).all()
        got[method] = a.proxy_mask
    assert got["random"].sum() == got["spread"].sum() and not np.array_equal(got["random"], got["spread"])


class TestEncodeErrors:
    def test_bad_knobs(self, tmp_path):
        m = tiny_model(50)
        for kw in ({"proxy_ratio": 0.0}, {"feature_bits": 17}, {"weights_dtype": "f8"}, {"zstd_level": 0},
                   {"cell_size": -1.0}, {"proxy_selection": "fps"}, {"nonsense": 1}):
            with pytest.raises(ProxycodecError):
                codec.encode(m, tmp_path / "x.pxc", **kw)
        assert not (tmp_path / "x.pxc").exists()

    def test_scene_sections_inconsistent_with_metadata(self, encoded, tmp_path):
        _, path, _ = encoded
        c = read_container(path)
        cases = {
            "wrong count": ({**c.meta, "anchors": {**c.meta["anchors"], "count": c.meta["anchors"]["count"] + 1}},
                            c.arrays),
            "missing section": (c.meta, {k: v for k, v in c.arrays.items() if k != "anchors/scalings"}),
            "wrong dtype": (c.meta, {**c.arrays, "proxy/features": c.arrays["proxy/features"].astype(np.uint16)}),
            "bad quant": ({**c.meta, "quant": {**c.meta["quant"], "features": {"bits": 8, "offset": [0.0]}}},
                          c.arrays),
            "future scene format": ({**c.meta, "scene_format": 99}, c.arrays),
            "not a scene": ({**c.meta, "kind": "proxycodec.weights"}, c.arrays),
            "garbage metadata": ({**c.meta, "positions": "grid"}, c.arrays),
            "missing weights": (c.meta, {k: v for k, v in c.arrays.items() if not k.startswith("predictor/")}),
        }
        for name, (meta, arrays) in cases.items():
            p = tmp_path / "bad.pxc"
            write_container(p, meta, arrays, level=1)
            with pytest.raises(ContainerError):
                codec.decode(p)


class TestStats:
    def test_container_stats_fields(self, encoded):
        model, path, report = encoded
        s = codec.stats(path)
        for k in ("anchors", "proxies", "leaves", "sections", "bits_per_anchor", "source_bytes", "ratio",
                  "format_version", "metadata", "file_bytes"):
            assert k in s, k
        assert s["anchors"] == model.scene.num_anchors == s["proxies"] + s["leaves"]
        assert s["file_bytes"] == path.stat().st_size
        assert s["header_and_toc_bytes"] + sum(x["stored_bytes"] for x in s["sections"]) == s["file_bytes"]
        assert s["format_version"] == 1 and s["metadata"]["kind"] == "proxycodec.scene"
        assert s["bits_per_anchor"] == pytest.approx(8 * s["file_bytes"] / s["anchors"])
        assert s["source_bytes"] > s["file_bytes"] and s["ratio"] == pytest.approx(s["source_bytes"] / s["file_bytes"])
        names = {x["name"] for x in s["sections"]}
        assert {"meta", "anchors/octree", "anchors/proxy_mask", "anchors/scalings", "proxy/features",
                "anchors/offsets"} <= names

    def test_ply_stats(self, tmp_path):
        m = tiny_model(60)
        ply, w = m.save(tmp_path / "s.ply")
        s = codec.stats(ply)
        assert s["type"] == "ply" and s["anchors"] == 60
        assert s["total_bytes"] == ply.stat().st_size + w.stat().st_size
        assert s["raw_bytes_by_group"]["features"] == 60 * 32 * 4


class TestCli:
    def test_encode_stats_decode_ply(self, tmp_path):
        m = tiny_model(150)
        ply, _ = m.save(tmp_path / "s.ply")
        run = CliRunner().invoke
        r = run(cli, ["encode", str(ply), "--no-distill", "--predictor-iters", "10", "--zstd-level", "3", "--seed", "1"])
        assert r.exit_code == 0, r.output
        pxc = tmp_path / "s.pxc"
        assert pxc.exists() and "predictor" in r.output  # progress lines (stderr is mixed in by CliRunner)
        r = run(cli, ["stats", str(pxc), "--json"])
        assert r.exit_code == 0 and json.loads(r.output)["anchors"] == 150
        r = run(cli, ["stats", str(pxc)])
        assert r.exit_code == 0 and "bits/anchor" in r.output and "proxy/features" in r.output
        assert "(scene format 6: octree)" in r.output
        r = run(cli, ["stats", str(ply)])
        assert r.exit_code == 0 and "150 anchors" in r.output
        cams = tmp_path / "cams.json"
        cams.write_text(json.dumps([c.to_json() for c in m.cameras[:1]]))
        out = tmp_path / "renders"
        r = run(cli, ["decode", str(pxc), "--res", "0.3,0.5", "--cameras", str(cams), "-o", str(out),
                      "--backend", "reference"])
        assert r.exit_code == 0, r.output
        assert sorted(p.name for p in out.iterdir()) == ["view000_res0.300.png", "view000_res0.500.png"]
        # An export renders nothing unless -o or --view asks; it takes one resolution.
        r = run(cli, ["decode", str(pxc), "--res", "0.5", "--ply", str(tmp_path / "g.ply")])
        assert r.exit_code == 0, r.output
        assert not (tmp_path / "s_renders").exists()
        from proxycodec.formats.inria_ply import read_inria_ply

        g = read_inria_ply(tmp_path / "g.ply")
        assert g.n_gaussians > 0 and g.sh_degree == 1
        assert np.allclose(np.linalg.norm(g.quats, axis=1), 1.0, atol=1e-5)
        r = run(cli, ["decode", str(pxc), "--res", "0.3,0.5", "--ply", str(tmp_path / "h.ply")])
        assert r.exit_code == 2 and "one resolution" in r.output

    def test_user_errors_are_one_line(self, tmp_path):
        m = tiny_model(50)
        ply, _ = m.save(tmp_path / "s.ply")
        run = CliRunner().invoke
        for args in (["encode", str(ply), "--proxy-ratio", "2"],
                     ["decode", str(ply)],
                     ["decode", str(tmp_path / "missing.pxc")],
                     ["stats", str(tmp_path / "missing.pxc")]):
            r = run(cli, args)
            assert r.exit_code == 2, (args, r.output)
            assert "Traceback" not in r.output and r.output.strip().count("\n") == 0, r.output
            assert r.output.startswith("error: ")


def test_wrongly_typed_metadata_is_our_error(tmp_path):
    """stats/decode of a container whose CRCs are valid but whose metadata has the wrong types."""
    from proxycodec import codec
    from proxycodec.formats.container import ContainerError, read_container, write_container

    src = tmp_path / "s.pxc"
    codec.encode(tiny_model(60), src, distill=False, predictor_iters=5)
    c = read_container(src)
    for patch in ({"source": 5}, {"source": {"bytes": "many"}}, {"anchors": []}):
        q = tmp_path / "q.pxc"
        write_container(q, {**c.meta, **patch}, c.arrays)
        with pytest.raises(ContainerError):
            codec.stats(q)
    meta = {**c.meta, "predictor": {**c.meta["predictor"], "dist_ref": 1e308}}
    write_container(tmp_path / "d.pxc", meta, c.arrays)
    with pytest.raises(ContainerError, match="dist_ref"):
        codec.decode(tmp_path / "d.pxc")


@pytest.mark.parametrize("dtype,levels", [("q8", 127), ("q5", 15)])
def test_int8_weights_round_trip_within_half_a_step_and_cameras_are_capped(tmp_path, dtype, levels):
    from proxycodec import codec
    from proxycodec.camera import orbit_cameras

    m = tiny_model(80)
    m.cameras = orbit_cameras((0.0, 0.0, 0.1), 1.5, 40, width=32, height=24)
    r = codec.encode(m, tmp_path / "q.pxc", distill=False, weights_dtype=dtype, predictor_iters=10, max_cameras=5)
    back = codec.decode(tmp_path / "q.pxc")
    for (k, a), (_, b) in zip(r.model.decoder.state_dict().items(), back.decoder.state_dict().items()):
        assert torch.equal(a, b), k  # decode == what encode reported, bit for bit
    for (k, w), (_, d) in zip(m.decoder.state_dict().items(), back.decoder.state_dict().items()):
        if w.ndim == 2:
            step = w.abs().amax(1, keepdim=True) / levels
            assert ((w - d).abs() <= step / 2 + 1e-7).all(), k
    assert [c.name for c in back.cameras] == [m.cameras[i].name for i in (0, 8, 16, 24, 32)]
    c = read_scene_container(tmp_path / "q.pxc")
    q = c.arrays["decoder/mlp_cov.2.weight"]
    assert q.dtype == np.int8 and c.meta["cameras_in_source"] == 40 and c.meta["weights_dtype"] == dtype
    assert np.abs(q.astype(int)).max() == levels  # every row's largest weight sits on the grid's end
    f16 = codec.encode(m, tmp_path / "h.pxc", distill=False, weights_dtype="f16", predictor_iters=10, max_cameras=5)
    assert r.file_bytes < f16.file_bytes
    if dtype != "q8":  # fewer levels: fewer bytes, and a coarser decoder
        q8 = codec.encode(m, tmp_path / "q8.pxc", distill=False, weights_dtype="q8", predictor_iters=10,
                          max_cameras=5)
        assert r.file_bytes < q8.file_bytes
        w8 = codec.decode(tmp_path / "q8.pxc").decoder.state_dict()
        err = {n: sum(float((w - b[k]).abs().sum()) for k, w in m.decoder.state_dict().items() if w.ndim == 2)
               for n, b in (("q8", w8), (dtype, back.decoder.state_dict()))}
        assert err[dtype] > 2 * err["q8"]
