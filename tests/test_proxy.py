"""Proxy selection, nearest-proxy assignment, the residual predictor and L_recon (proxycodec.proxy)."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch

from proxycodec.errors import ProxycodecError
from proxycodec.proxy import (
    PredictorConfig, ResidualPredictor, TrainConfig, default_cell_size, nearest_proxy, predictor_inputs,
    recon_loss, select_proxies, train_predictor,
)


def grid_points(n=400, size=(16, 16, 4), voxel=0.05, seed=0) -> np.ndarray:
    """``n`` distinct anchors on a voxel grid (float32, as Scaffold-GS stores them)."""
    rng = np.random.default_rng(seed)
    cells = np.stack(np.meshgrid(*[np.arange(s) for s in size], indexing="ij"), -1).reshape(-1, 3)
    pick = rng.choice(len(cells), n, replace=False)
    return (cells[pick] * voxel).astype(np.float32)


class TestSelectProxies:
    @pytest.mark.parametrize("ratio", [0.3, 0.1, 0.5, 1 / 3, 1.0])
    def test_per_cell_count_is_ceil_rho_n(self, ratio):
        p = grid_points(600)
        eps = 0.15
        mask = select_proxies(p, eps, ratio, seed=3)
        cells = np.floor(p.astype(np.float64) / eps).astype(np.int64)
        _, inv = np.unique(cells, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        for c in range(inv.max() + 1):
            members = inv == c
            n = int(members.sum())
            assert int(mask[members].sum()) == math.ceil(Fraction(str(ratio)) * n if ratio != 1 / 3
                                                         else Fraction(1, 3) * n)

    def test_every_occupied_cell_has_a_proxy(self):
        p = grid_points(300)
        mask = select_proxies(p, 0.1, 0.05, seed=0)
        cells = np.floor(p.astype(np.float64) / 0.1).astype(np.int64)
        occupied = {tuple(c) for c in cells}
        with_proxy = {tuple(c) for c in cells[mask]}
        assert occupied == with_proxy

    def test_seed_deterministic_and_seed_dependent(self):
        p = grid_points(500)
        a = select_proxies(p, 0.15, 0.3, seed=7)
        b = select_proxies(p, 0.15, 0.3, seed=7)
        c = select_proxies(p, 0.15, 0.3, seed=8)
        assert np.array_equal(a, b)
        assert not np.array_equal(a, c)
        assert a.sum() == c.sum()  # the count per cell does not depend on the seed

    def test_independent_of_input_order(self):
        p = grid_points(500)
        perm = np.random.default_rng(1).permutation(len(p))
        a = select_proxies(p, 0.15, 0.3, seed=2)
        b = select_proxies(p[perm], 0.15, 0.3, seed=2)
        assert np.array_equal(a[perm], b)

    def test_accepts_tensors_and_rejects_bad_parameters(self):
        p = grid_points(50)
        assert np.array_equal(select_proxies(torch.from_numpy(p), 0.1, 0.3, 0), select_proxies(p, 0.1, 0.3, 0))
        with pytest.raises(ProxycodecError):
            select_proxies(p, 0.1, 0.0, 0)
        with pytest.raises(ProxycodecError):
            select_proxies(p, -1.0, 0.3, 0)
        assert select_proxies(np.zeros((0, 3)), 0.1, 0.3, 0).shape == (0,)

    @pytest.mark.parametrize("ratio", [0.3, 0.1, 0.5, 1.0])
    def test_spread_keeps_the_counts_and_is_order_independent(self, ratio):
        p = grid_points(600)
        a = select_proxies(p, 0.15, ratio, seed=3, method="spread")
        r = select_proxies(p, 0.15, ratio, seed=3)
        cells = np.unique(np.floor(p.astype(np.float64) / 0.15).astype(np.int64), axis=0, return_inverse=True)[1]
        cells = cells.reshape(-1)
        assert np.array_equal(np.bincount(cells, a), np.bincount(cells, r))  # ceil(rho n) per cell, as random
        perm = np.random.default_rng(1).permutation(len(p))
        assert np.array_equal(a[perm], select_proxies(p[perm], 0.15, ratio, seed=3, method="spread"))
        assert np.array_equal(a, select_proxies(p, 0.15, ratio, seed=99, method="spread"))  # seed-free

    @staticmethod
    def greedy_k_median(p, eps, ratio):
        """Reference: per cell, anchors in lexicographic order, k greedy steps, each adding the candidate with the
        smallest sum of distances to the nearest pick (first such candidate on ties)."""
        p = p.astype(np.float64)
        keys = [tuple(k) for k in np.floor(p / eps).astype(np.int64)]
        mask = np.zeros(len(p), dtype=bool)
        for key in set(keys):
            idx = [i for i in range(len(p)) if keys[i] == key]
            idx.sort(key=lambda i: tuple(p[i]))
            k = math.ceil(Fraction(str(ratio)) * len(idx))
            cur = [math.inf] * len(idx)
            picked = set()
            for _ in range(k):
                best, best_cost = None, math.inf
                for j in range(len(idx)):
                    if j in picked:
                        continue
                    cost = sum(min(cur[t], float(np.linalg.norm(p[idx[t]] - p[idx[j]]))) for t in range(len(idx)))
                    if cost < best_cost:
                        best, best_cost = j, cost
                picked.add(best)
                cur = [min(cur[t], float(np.linalg.norm(p[idx[t]] - p[idx[best]]))) for t in range(len(idx))]
            mask[[idx[j] for j in picked]] = True
        return mask

    @pytest.mark.parametrize("seed", [0, 1])
    def test_spread_matches_a_greedy_k_median_reference(self, seed):
        rng = np.random.default_rng(seed)
        p = rng.normal(size=(160, 3)).astype(np.float32)  # off-grid: no distance ties
        got = select_proxies(p, 0.7, 0.3, seed=0, method="spread")
        assert np.array_equal(got, self.greedy_k_median(p, 0.7, 0.3))

    def test_spread_falls_back_to_random_in_oversized_cells(self, monkeypatch):
        p = grid_points(300)
        monkeypatch.setattr("proxycodec.proxy.SPREAD_MAX_CELL", 0)
        assert np.array_equal(select_proxies(p, 0.15, 0.3, seed=5, method="spread"),
                              select_proxies(p, 0.15, 0.3, seed=5))

    def test_spread_puts_leaves_closer_to_their_proxies(self):
        p = grid_points(1500, size=(24, 24, 6))
        dist = {}
        for method in ("random", "spread"):
            mask = select_proxies(p, 0.2, 0.3, seed=0, method=method)
            near = nearest_proxy(p, mask)
            dist[method] = float(np.linalg.norm(p - p[near], axis=1)[~mask].mean())
        assert dist["spread"] < 0.95 * dist["random"]

    def test_unknown_selection_is_refused(self):
        with pytest.raises(ProxycodecError, match="proxy selection"):
            select_proxies(grid_points(20), 0.1, 0.3, 0, method="fps")

    def test_default_cell_size_holds_about_ten_anchors(self):
        voxel = 0.05
        cells = np.stack(np.meshgrid(np.arange(40), np.arange(40), [0], indexing="ij"), -1).reshape(-1, 3)
        p = (cells * voxel).astype(np.float32)  # a dense plane: m x m anchors per cell
        eps = default_cell_size(p, voxel)
        m = eps / voxel
        assert m == pytest.approx(3)  # 9 per cell is the closest to 10
        cells_used = np.unique(np.floor(p / eps), axis=0)
        assert 6 <= len(p) / len(cells_used) <= 15


class TestNearestProxy:
    def brute(self, p, mask):
        p = p.astype(np.float64)
        pidx = np.flatnonzero(mask)
        out = np.arange(len(p))
        for i in np.flatnonzero(~mask):
            d = ((p[pidx] - p[i]) ** 2).sum(1)
            out[i] = pidx[d == d.min()].min()
        return out

    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_matches_brute_force_with_ties_to_smallest_index(self, seed):
        p = grid_points(300, size=(10, 10, 3), seed=seed)  # a grid: equidistant proxies everywhere
        mask = select_proxies(p, 0.15, 0.3, seed)
        assert np.array_equal(nearest_proxy(p, mask, "index"), self.brute(p, mask))

    @pytest.mark.parametrize("seed,ties", [(0, "index"), (1, "index"), (0, "position"), (1, "position")])
    def test_kd_tree_path_equals_exhaustive_path(self, seed, ties, monkeypatch):
        import proxycodec.proxy as proxy

        p = grid_points(400, size=(10, 10, 4), seed=seed)
        mask = select_proxies(p, 0.15, 0.3, seed)
        exhaustive = nearest_proxy(p, mask, ties)
        monkeypatch.setattr(proxy, "BRUTE_FORCE_PAIRS", 0)
        assert np.array_equal(nearest_proxy(p, mask, ties), exhaustive)

    def test_many_ties_beyond_the_candidate_list(self, monkeypatch):
        import proxycodec.proxy as proxy

        monkeypatch.setattr(proxy, "BRUTE_FORCE_PAIRS", 0)
        # A leaf at the centre of a ring of 24 equidistant proxies: more ties than the kd-tree candidates.
        ang = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        ring = np.c_[np.cos(ang), np.sin(ang), np.zeros(24)]
        p = np.concatenate([ring, [[0.0, 0.0, 0.0]]])
        mask = np.r_[np.ones(24, bool), False]
        assert np.array_equal(nearest_proxy(p, mask, "index"), self.brute(p, mask))

    @pytest.mark.parametrize("k", [2, 3, 5])
    def test_k_nearest_in_distance_then_index_order_on_both_paths(self, k, monkeypatch):
        import proxycodec.proxy as proxy
        from proxycodec.proxy import nearest_proxies

        p = grid_points(300, size=(10, 10, 3), seed=k)  # a grid: many equidistant proxies
        mask = select_proxies(p, 0.15, 0.3, k)
        got = nearest_proxies(p, mask, k, "index")
        pidx = np.flatnonzero(mask)
        for i in range(len(p)):
            if mask[i]:
                assert (got[i] == i).all()
                continue
            d = ((p[pidx].astype(np.float64) - p[i]) ** 2).sum(1)
            assert np.array_equal(got[i], pidx[np.lexsort((pidx, d))][:k]), i
        assert np.array_equal(got[:, 0], nearest_proxy(p, mask, "index"))
        monkeypatch.setattr(proxy, "BRUTE_FORCE_PAIRS", 0)
        assert np.array_equal(nearest_proxies(p, mask, k, "index"), got)
        few = np.zeros(len(p), bool)
        few[[3, 7]] = True  # k beyond the number of proxies: the farthest one repeats
        two = nearest_proxies(p, few, 4)
        assert set(two[0]) <= {3, 7} and (two[~few][:, 2:] == two[~few][:, 1:2]).all()

    @pytest.mark.parametrize("k", [1, 4])
    def test_position_ties_follow_the_position_and_not_the_storage_order(self, k, monkeypatch):
        """With ties="position" equidistant proxies are ordered by (x, y, z): the neighbours of every anchor are the
        same whatever order the anchors are stored in (a trainer's order and the container's Morton order), on
        both search paths; with "index" (files written before the rule) they are not, on a grid."""
        import proxycodec.proxy as proxy
        from proxycodec.proxy import nearest_proxies

        p = grid_points(300, size=(10, 10, 3), seed=k)
        mask = select_proxies(p, 0.15, 0.3, k)
        got = nearest_proxies(p, mask, k, "position")
        pidx = np.flatnonzero(mask)
        q = p[pidx].astype(np.float64)
        for i in np.flatnonzero(~mask):  # reference: distance, then x, then y, then z
            d = ((q - p[i]) ** 2).sum(1)
            assert np.array_equal(got[i], pidx[np.lexsort((q[:, 2], q[:, 1], q[:, 0], d))][:k]), i
        perm = np.random.default_rng(k).permutation(len(p))
        moved = nearest_proxies(p[perm], mask[perm], k, "position")
        assert np.array_equal(perm[moved], got[perm])
        moved_index = nearest_proxies(p[perm], mask[perm], k, "index")
        assert not np.array_equal(perm[moved_index], nearest_proxies(p, mask, k, "index")[perm])
        monkeypatch.setattr(proxy, "BRUTE_FORCE_PAIRS", 0)
        assert np.array_equal(nearest_proxies(p, mask, k, "position"), got)
        with pytest.raises(ProxycodecError, match="tie rule"):
            nearest_proxies(p, mask, k, "nearest")

    @pytest.mark.parametrize("k", [1, 4])
    def test_grid_ties_survive_moving_and_scaling_the_anchors(self, k, monkeypatch):
        """A conversion trains in a canonical frame and stores world coordinates (x 10.77, moved, float32): under
        "grid" (lattice unit scaled alike) every anchor keeps the neighbours it had, on both search paths, and they
        are the exact "position" order of the grid; "position" on the moved float32 coordinates loses some."""
        import proxycodec.proxy as proxy
        from proxycodec.proxy import nearest_proxies

        voxel, s, c = 0.05, 10.77029200363159, np.array([-0.0748, 1.4511, 4.5864])
        p = grid_points(300, size=(10, 10, 3), voxel=voxel, seed=k) + np.float32(0.5 * voxel)  # voxel centres
        mask = select_proxies(p, 0.15, 0.3, k)
        world = (p.astype(np.float64) * s + c).astype(np.float32)
        exact = nearest_proxies(np.round(p / voxel * 2), mask, k, "position")  # integer lattice: exact ties
        assert np.array_equal(nearest_proxies(p, mask, k, "grid", voxel), exact)
        assert np.array_equal(nearest_proxies(world, mask, k, "grid", voxel * s), exact)
        assert not np.array_equal(nearest_proxies(world, mask, k, "position"), exact)
        monkeypatch.setattr(proxy, "BRUTE_FORCE_PAIRS", 0)
        assert np.array_equal(nearest_proxies(world, mask, k, "grid", voxel * s), exact)
        for unit in (None, 0.0, float("nan")):
            with pytest.raises(ProxycodecError, match="length unit"):
                nearest_proxies(world, mask, k, "grid", unit)

    def test_predictor_configurations_written_before_the_tie_rule_read_as_index(self):
        from proxycodec.proxy import PredictorConfig, ProxyLeafConfig

        assert PredictorConfig().ties == "grid" and PredictorConfig.from_json(PredictorConfig().to_json()).ties \
            == "grid"
        assert PredictorConfig.from_json(PredictorConfig(ties="position").to_json()).ties == "position"
        old = {k: v for k, v in PredictorConfig(context=4).to_json().items() if k != "ties"}
        assert PredictorConfig.from_json(old).ties == "index"
        old_pl = {k: v for k, v in ProxyLeafConfig().to_json().items() if k != "ties"}
        assert ProxyLeafConfig.from_json(old_pl).ties == "index"
        with pytest.raises(ProxycodecError, match="ties"):
            PredictorConfig(ties="random")

    def test_proxies_map_to_themselves_and_no_proxy_is_an_error(self):
        p = grid_points(50)
        mask = np.zeros(50, bool)
        mask[::3] = True
        nn = nearest_proxy(p, mask)
        assert np.array_equal(nn[mask], np.flatnonzero(mask))
        assert mask[nn].all()
        with pytest.raises(ProxycodecError):
            nearest_proxy(p, np.zeros(50, bool))


def smooth_scene(n=500, seed=0):
    p = grid_points(n, seed=seed)
    rng = np.random.default_rng(seed)
    freq = rng.normal(size=(32, 3)) * 2.0
    feats = np.sin(p.astype(np.float64) @ freq.T + rng.uniform(0, 6.28, 32)).astype(np.float32)
    return torch.from_numpy(p), torch.from_numpy(feats)


class TestPredictor:
    def test_untrained_predictor_is_the_proxy_copy(self):
        pos, feats = smooth_scene(100)
        mask = select_proxies(pos, 0.15, 0.3, 0)
        nn = torch.from_numpy(nearest_proxy(pos, mask))
        leaves = torch.from_numpy(np.flatnonzero(~mask))
        pred = ResidualPredictor(PredictorConfig(dist_ref=0.05))
        f, o = pred.predict(pos, feats, nn, leaves)
        assert o is None
        assert torch.equal(f, feats[nn[leaves]])

    def test_training_beats_the_proxy_copy_baseline(self):
        torch.manual_seed(0)
        pos, feats = smooth_scene(500)
        mask = select_proxies(pos, 0.15, 0.3, 0)
        pred = ResidualPredictor(PredictorConfig(hidden=32, dist_ref=0.05))
        r = train_predictor(pred, pos, feats, mask, config=TrainConfig(iters=150, lr=3e-3))
        # the baseline is the proxy-copy prediction over all leaves (neighbours under the predictor's rule)
        nn = nearest_proxy(pos, mask, pred.config.ties, pred.config.dist_ref)
        leaves = np.flatnonzero(~mask)
        base = float(recon_loss(feats[nn[leaves]], feats[leaves]))
        assert r.baseline_loss == pytest.approx(base, rel=1e-5)
        assert r.final_loss < 0.7 * r.baseline_loss
        assert not pred.training

    def test_context_of_more_proxies_predicts_better(self):
        """context > 1: the next nearest proxies' features (relative to the nearest) and geometry are inputs; the
        untrained predictor is still the nearest-proxy copy, and a trained one beats the 1-proxy predictor."""
        from proxycodec.proxy import nearest_proxies

        pos, feats = smooth_scene(600, seed=4)
        mask = select_proxies(pos, 0.15, 0.3, 0)
        leaves = torch.from_numpy(np.flatnonzero(~mask))
        near3 = torch.from_numpy(nearest_proxies(pos, mask, 3))
        torch.manual_seed(0)
        pred3 = ResidualPredictor(PredictorConfig(hidden=32, dist_ref=0.05, context=3))
        assert pred3.encoder[0].in_features == 32 + 3 * pred3.config.n_geo + 2 * 32
        f, _ = pred3.predict(pos, feats, near3, leaves)
        assert torch.equal(f, feats[near3[leaves, 0]])
        with pytest.raises(ProxycodecError, match="sees 3 proxies"):
            pred3.predict(pos, feats, near3[:, :1], leaves)
        losses = []
        for ctx in (1, 3):
            torch.manual_seed(0)
            pred = ResidualPredictor(PredictorConfig(hidden=32, dist_ref=0.05, context=ctx))
            losses.append(train_predictor(pred, pos, feats, mask, config=TrainConfig(iters=300, lr=3e-3)).final_loss)
        assert losses[1] < 0.95 * losses[0]
        with pytest.raises(ProxycodecError, match="context"):
            PredictorConfig(context=0)
        assert PredictorConfig.from_json({**PredictorConfig(context=3).to_json()}).context == 3
        assert PredictorConfig.from_json({k: v for k, v in PredictorConfig().to_json().items()
                                          if k != "context"}).context == 1  # older files

    def test_kept_encodings_predict_as_the_computed_ones(self):
        """Stage 2 keeps every anchor's proxy -> leaf encodings (``proxy_encodings``) and takes rows from them: the
        predictions and the features' gradients are those of encodings computed per call, for any leaf subset."""
        from proxycodec.proxy import nearest_proxies, proxy_encodings

        pos, feats = smooth_scene(300, seed=2)
        mask = select_proxies(pos, 0.15, 0.3, 0)
        near = torch.from_numpy(nearest_proxies(pos, mask, 3))
        torch.manual_seed(0)
        pred = ResidualPredictor(PredictorConfig(hidden=16, dist_ref=0.05, context=3))
        with torch.no_grad():
            pred.head.weight.normal_(0, 0.3)  # away from the proxy-copy start, so the geometry matters
        pos_t = torch.as_tensor(pos)
        enc = proxy_encodings(pos_t, near, pred.config)
        assert enc.shape == (len(pos), 3, pred.config.n_geo) and not enc.requires_grad
        leaves = torch.from_numpy(np.flatnonzero(~mask)[::3].copy())
        outs = []
        for e in (None, enc):
            f = feats.clone().requires_grad_(True)
            p, _ = pred.predict(pos_t, f, near, leaves, encodings=e)
            (g,) = torch.autograd.grad((p ** 2).sum(), f)
            outs.append((p.detach(), g))
        assert torch.allclose(outs[0][0], outs[1][0], rtol=1e-6, atol=1e-6)
        assert torch.allclose(outs[0][1], outs[1][1], rtol=1e-5, atol=1e-5) and outs[0][1].abs().sum() > 0
        assert not torch.allclose(outs[0][0], feats[near[leaves, 0]], atol=1e-3)  # not the copy baseline
        # a row's encoding is its own, whichever rows are asked for
        assert torch.allclose(proxy_encodings(pos_t, near, pred.config, leaves), enc[leaves], rtol=1e-6, atol=1e-7)

    def test_offsets_prediction_shapes_and_training(self):
        pos, feats = smooth_scene(200)
        offs = torch.randn(200, 10, 3) * 0.1
        mask = select_proxies(pos, 0.15, 0.3, 0)
        pred = ResidualPredictor(PredictorConfig(predict_offsets=True, hidden=16, n_blocks=1, dist_ref=0.05))
        r = train_predictor(pred, pos, feats, mask, offsets=offs, config=TrainConfig(iters=20))
        assert r.final_loss <= r.baseline_loss * 1.01
        nn = torch.from_numpy(nearest_proxy(pos, mask))
        leaves = torch.from_numpy(np.flatnonzero(~mask))
        f, o = pred.predict(pos, feats, nn, leaves, offs)
        assert f.shape == (len(leaves), 32) and o.shape == (len(leaves), 10, 3)
        with pytest.raises(ProxycodecError):
            train_predictor(pred, pos, feats, mask, config=TrainConfig(iters=1))

    @pytest.mark.parametrize("kind", ["residual", "residual-context-3-offsets", "proxy-leaf-mlp"])
    def test_backward_into_proxy_features_is_bit_identical(self, kind):
        """Thousands of leaves share a few proxies, so the gather of proxy rows repeats indices. Advanced indexing's
        backward adds the repeats with parallel atomic adds on CPU, in a run-dependent order (it made stage-2 fits
        diverge); the predictors gather with ``index_select``, whose backward adds them in index order."""
        from proxycodec.proxy import ProxyLeafConfig, ProxyLeafMLP, nearest_proxies

        g = torch.Generator().manual_seed(0)
        n = 6000
        pos = torch.rand(n, 3, generator=g)
        mask = np.zeros(n, bool)
        mask[:400] = True  # ~14 leaves per proxy: every proxy row is gathered many times
        ctx = 3 if "context" in kind else 1
        near = torch.from_numpy(nearest_proxies(pos.numpy(), mask, ctx))
        leaves = torch.from_numpy(np.flatnonzero(~mask))
        torch.manual_seed(0)
        if kind == "proxy-leaf-mlp":
            pred = ProxyLeafMLP(ProxyLeafConfig(hidden=16, n_blocks=1))
        else:
            pred = ResidualPredictor(PredictorConfig(hidden=16, n_blocks=1, dist_ref=0.05, context=ctx,
                                                     predict_offsets=ctx > 1))
        for p in pred.parameters():
            torch.nn.init.normal_(p, std=0.1)
        feats = torch.randn(n, 32, generator=g).requires_grad_(True)
        offs = (0.1 * torch.randn(n, 10, 3, generator=g)).requires_grad_(True)
        w = torch.randn(len(leaves), 32, generator=g)

        def grads():
            feats.grad = offs.grad = None
            f, o = pred.predict(pos, feats, near, leaves, offs)
            loss = (f * w).sum() + (o.square().sum() if o is not None else 0.0)
            loss.backward()
            return feats.grad.clone(), None if offs.grad is None else offs.grad.clone()

        first = grads()
        for _ in range(6):
            again = grads()
            assert torch.equal(again[0], first[0])
            assert (again[1] is None) == (first[1] is None)
            assert again[1] is None or torch.equal(again[1], first[1])

    def test_state_arrays_round_trip_and_bad_weights(self):
        cfg = PredictorConfig(hidden=16, n_blocks=2, dist_ref=0.1)
        a = ResidualPredictor(cfg)
        for p in a.parameters():
            torch.nn.init.normal_(p)
        b = ResidualPredictor.from_arrays(cfg, a.state_arrays())
        x, g = torch.randn(5, 32), torch.randn(5, cfg.n_in - 32)
        assert torch.equal(a(x, g)[0], b(x, g)[0])
        arr = a.state_arrays()
        with pytest.raises(ProxycodecError, match="missing"):
            ResidualPredictor.from_arrays(cfg, {k: v for k, v in arr.items() if k != "head.bias"})
        with pytest.raises(ProxycodecError, match="shape"):
            ResidualPredictor.from_arrays(cfg, {**arr, "head.bias": np.zeros(3, np.float32)})
        with pytest.raises(ProxycodecError, match="NaN"):
            ResidualPredictor.from_arrays(cfg, {**arr, "head.bias": np.full(32, np.nan, np.float32)})

    def test_config_json_round_trip_and_validation(self):
        cfg = PredictorConfig(hidden=48, n_blocks=3, predict_offsets=True, dist_ref=0.01)
        assert PredictorConfig.from_json(cfg.to_json()) == cfg
        for bad in ({"hidden": 0}, {"hidden": "64"}, {"n_blocks": 1.5}, {"dist_ref": -1}, {"predict_offsets": 1}):
            with pytest.raises(ProxycodecError):
                PredictorConfig.from_json({**cfg.to_json(), **bad})

    def test_inputs_are_finite_for_coincident_points(self):
        x = torch.zeros(3, 3)
        g = predictor_inputs(x, x, 0.05, 4, 4)
        assert torch.isfinite(g).all() and g.shape == (3, 9 + 27)


class TestReconLoss:
    def test_formula(self):
        a, b = torch.randn(7, 32), torch.randn(7, 32)
        want = ((a - b) ** 2).sum(1).mean() + 0.1 * (1 - torch.nn.functional.cosine_similarity(a, b, dim=1)).mean()
        assert torch.allclose(recon_loss(a, b), want)
        assert float(recon_loss(a, a)) == pytest.approx(0.0, abs=1e-6)
        assert float(recon_loss(a[:0], b[:0])) == 0.0

    def test_gradient_is_finite_at_zero_vectors(self):
        a = torch.zeros(4, 32, requires_grad=True)
        recon_loss(a, torch.zeros(4, 32)).backward()
        assert torch.isfinite(a.grad).all()

    def test_shape_mismatch(self):
        with pytest.raises(ProxycodecError):
            recon_loss(torch.zeros(3, 32), torch.zeros(3, 31))
