"""Features at arbitrary 3D points (``proxycodec.query_features``, supplement section 8.1) and the benchmark script
that reproduces the supplement's analysis on a tiny container."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import proxycodec
from proxycodec import codec
from proxycodec.errors import ProxycodecError
from proxycodec.model import SceneModel
from proxycodec.netconfig import PredictorConfig
from proxycodec.proxy import ResidualPredictor, nearest_proxies, predictor_inputs, predictor_neighbours, select_proxies
from proxycodec.query import FeatureField, query_features
from test_codec import FAST, tiny_model

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[1]


def film_model(seed: int = 0) -> SceneModel:
    """The codec tests' tiny scene with a FiLM embedding that does something (its output layer starts at zero)."""
    m = tiny_model(seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    last = m.decoder.mlp_embed[2]
    with torch.no_grad():
        last.weight.copy_(0.2 * torch.randn(last.weight.shape, generator=g))
        last.bias.copy_(0.1 * torch.randn(last.bias.shape, generator=g))
    return m


@pytest.fixture(scope="module")
def container(tmp_path_factory):
    path = tmp_path_factory.mktemp("query") / "tiny.pxc"
    codec.encode(film_model(), path, **{**FAST, "predictor_iters": 40})
    return path


@pytest.fixture(scope="module")
def container_context1(tmp_path_factory):
    """The paper's predictor, which sees the nearest proxy only (encode's default sees 4): its zero-offset answer
    at a proxy has the closed form the test below writes out."""
    path = tmp_path_factory.mktemp("query1") / "tiny1.pxc"
    codec.encode(film_model(), path, **{**FAST, "predictor_iters": 40, "predictor_context": 1})
    return path


def embedded(model: SceneModel, xi: float, rows=None) -> np.ndarray:
    s = model.scene
    rows = slice(None) if rows is None else torch.as_tensor(rows)
    with torch.no_grad():
        return model.decoder.embed(s.positions[rows], s.features[rows], xi).numpy()


def test_at_leaves_the_query_is_the_decoded_leaf_and_film_is_applied(container):
    decoded = codec.decode(container)
    mask = decoded.scene.metadata["proxy_mask"]
    leaves = np.flatnonzero(~mask)
    pos = decoded.scene.positions.numpy()
    for xi in (0.1, 0.5, 1.0):
        q = query_features(container, pos[leaves], xi)
        assert q.dtype == np.float32 and q.shape == (len(leaves), 32)
        np.testing.assert_allclose(q, embedded(decoded, xi, leaves), rtol=0, atol=2e-6)
    # the embedding is not the identity here, and depends on xi
    raw = FeatureField.open(container).predict(pos[leaves])
    np.testing.assert_allclose(raw, decoded.scene.features.numpy()[leaves], rtol=0, atol=2e-6)
    assert np.abs(query_features(container, pos[leaves], 0.1) - raw).max() > 0.05
    assert np.abs(query_features(container, pos[leaves], 0.1) - query_features(container, pos[leaves], 1.0)).max() > 0.01


def test_at_proxies_the_stored_feature_or_the_predictor_at_zero_offset(container_context1):
    cs = codec.load(container_context1)
    decoded = cs.to_model()
    mask = decoded.scene.metadata["proxy_mask"]
    prox = np.flatnonzero(mask)
    pos = decoded.scene.positions.numpy()
    field = FeatureField.open(cs)
    # default: the anchor that formed there is the proxy itself, so every anchor position gives the decoded scene
    np.testing.assert_allclose(field.query(pos, 0.3), embedded(decoded, 0.3), rtol=0, atol=2e-6)
    assert np.array_equal(field.predict(pos[prox]), decoded.scene.features.numpy()[prox])
    # exact_proxies=False: the predictor's answer for a zero offset, which is not the stored feature
    zero = field.predict(pos[prox], exact_proxies=False)
    pred = cs.predictor()
    f = decoded.scene.features[torch.from_numpy(prox)]
    p = decoded.scene.positions[torch.from_numpy(prox)]
    c = pred.config
    with torch.no_grad():
        want = pred(f, predictor_inputs(p, p, c.dist_ref, c.pe_dist_freqs, c.pe_dir_freqs))[0].numpy()
    np.testing.assert_allclose(zero, want, rtol=0, atol=2e-6)
    assert np.abs(zero - f.numpy()).max() > 1e-3


def test_between_anchors_the_nearest_proxy_decides(container):
    decoded = codec.decode(container)
    s = decoded.scene
    mask = s.metadata["proxy_mask"]
    rng = np.random.default_rng(0)
    lo, hi = s.bounds()
    pts = rng.uniform(lo, hi, (200, 3)).astype(np.float32)
    field = FeatureField.open(container)
    raw = field.predict(pts)
    # the same as the predictor run on the points as if they were leaves of the decoded scene
    allpos = np.concatenate([s.positions.numpy(), pts])
    m = np.concatenate([mask, np.zeros(len(pts), bool)])
    pred = codec.load(container).predictor()
    assert pred.config.context == 4  # encode's default: the points' context proxies are found as the leaves' are
    near = torch.from_numpy(nearest_proxies(allpos, m, pred.config.context, pred.config.ties, pred.config.dist_ref))
    feats = torch.cat([s.features, torch.zeros(len(pts), 32)])
    offs = torch.cat([s.offsets, torch.zeros(len(pts), 10, 3)])
    with torch.no_grad():
        want = pred.predict(torch.from_numpy(allpos), feats, near,
                                                           torch.arange(len(mask), len(allpos)), offs)[0]
    np.testing.assert_allclose(raw, want.numpy(), rtol=0, atol=2e-6)
    # points in the same place give the same answer, whatever else is queried with them (and in any order)
    again = field.predict(pts[::-1].copy())[::-1]
    np.testing.assert_allclose(again, raw, rtol=0, atol=2e-6)
    assert field.predict(np.zeros((0, 3))).shape == (0, 32)


def test_sources_model_with_predictor_and_fitted_ply(container, tmp_path):
    cs = codec.load(container)
    decoded = cs.to_model()
    pos = decoded.scene.positions.numpy()[:50] + np.float32(0.013)
    ref = query_features(container, pos, 0.4)
    assert np.array_equal(query_features(cs, pos, 0.4), ref)
    assert np.array_equal(query_features(decoded, pos, 0.4, predictor=cs.predictor()), ref)
    assert np.array_equal(proxycodec.query_features(container, torch.from_numpy(pos), 0.4), ref)
    with pytest.raises(ProxycodecError, match="predictor"):
        query_features(decoded, pos, 0.4)
    # an anchor PLY whose sidecar holds a stage-2 predictor and proxy mask (what `fit` writes)
    m = film_model()
    s = m.scene
    mask = select_proxies(s.positions.numpy(), 0.15, 0.3, 0, "random")
    torch.manual_seed(0)
    pred = ResidualPredictor(PredictorConfig(hidden=16, n_blocks=1, dist_ref=s.voxel_size))
    with torch.no_grad():
        pred.head.weight.normal_(0, 0.1)
    arrays = {"proxy_mask": mask.astype(np.uint8), **{f"predictor/{k}": v for k, v in pred.state_arrays().items()}}
    ply, _ = m.save(tmp_path / "fitted.ply", extra_meta={"fit": {"predictor": pred.config.to_json()}},
                    extra_arrays=arrays)
    leaves = np.flatnonzero(~mask)
    with torch.no_grad():
        want_raw = pred.predict(s.positions, s.features, torch.from_numpy(predictor_neighbours(s.positions, mask,
                                                                                               pred.config)),
                                torch.from_numpy(leaves))[0]
        want = m.decoder.embed(s.positions[leaves], want_raw, 0.7).numpy()
    got = query_features(ply, s.positions.numpy()[leaves], 0.7)
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
    # an anchor PLY without one
    plain, _ = film_model().save(tmp_path / "plain.ply")
    with pytest.raises(ProxycodecError, match=r"plain\.ply: has no stage-2 residual predictor"):
        query_features(plain, pos, 0.5)
    with pytest.raises(ProxycodecError, match="no such file"):
        query_features(tmp_path / "missing.pxc", pos, 0.5)


@pytest.mark.parametrize("points, match", [
    (np.array([[0.0, 0.0, np.nan]]), r"NaN or infinity \(1 of 1 rows, first row 0\)"),
    (np.array([[0.0, 0.0, 0.0], [np.inf, 0.0, 0.0]]), "first row 1"),
    (np.zeros((4, 2)), r"\[N, 3\] array, got shape \(4, 2\)"),
    (np.zeros(3), r"got shape \(3,\)"),
    ([["a", "b", "c"]], "array of numbers"),
    (np.full((1, 3), 1e300), "float32 range"),
])
def test_bad_points_are_one_line_errors(container, points, match):
    with pytest.raises(ProxycodecError, match=match) as e:
        query_features(container, points, 0.5)
    assert "\n" not in str(e.value)


def test_bad_xi(container):
    with pytest.raises(ProxycodecError, match="outside"):
        query_features(container, np.zeros((1, 3)), 5.0)
    with pytest.raises(ProxycodecError, match="outside"):
        query_features(container, np.zeros((1, 3)), float("nan"))


# ------------------------------------------------------------------------------ the benchmark script
def test_feature_query_benchmark_on_a_tiny_container(container, tmp_path):
    sys.path.insert(0, str(REPO / "benchmarks"))
    try:
        import feature_query
    finally:
        sys.path.remove(str(REPO / "benchmarks"))
    out = tmp_path / "fq"
    rc = feature_query.main([str(container), "-o", str(out), "--points", "400", "--xi", "0.1,0.5,1.0",
                             "--seed", "3"])
    assert rc == 0
    res = json.loads((out / "feature_query.json").read_text())
    assert (out / "feature_query.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert res["points"] == 400 and res["k"] == 3 and res["seed"] == 3 and res["xi"] == [0.1, 0.5, 1.0]
    assert res["machine"]["cpu_count"] and res["versions"]["torch"] == torch.__version__
    per = {r["xi"]: r for r in res["per_xi"]}
    for r in per.values():
        assert sum(r["cluster_sizes"]) == 400 and len(r["cluster_sizes"]) == 3
        assert r["inertia"] > 0 and 0 <= r["pca_explained"][0] <= 1
    ch = res["changes"]["0.1->1"]
    assert 0.0 <= ch["fraction_changed"] <= 1.0 and ch["points_changed"] == round(ch["fraction_changed"] * 400)
    assert res["fraction_changed_0.1_to_1.0"] == ch["fraction_changed"]
    # the figures are those of the clusters it reports: recompute the change from the stored labels
    labels = np.load(out / "feature_query_labels.npz")
    a, b = labels["xi_0.1"], labels["xi_1"]
    assert len(a) == 400 and ch["points_changed"] == int((a != feature_query.match_labels(a, b, 3)).sum())
    # deterministic for a seed
    rc = feature_query.main([str(container), "-o", str(tmp_path / "fq2"), "--points", "400", "--xi", "0.1,0.5,1.0",
                             "--seed", "3"])
    res2 = json.loads((tmp_path / "fq2" / "feature_query.json").read_text())
    assert res2["per_xi"] == res["per_xi"] and res2["changes"] == res["changes"]
