"""Features at arbitrary 3D points, clustered across resolutions (the supplement's section 8.1 analysis).

    python benchmarks/feature_query.py scene.pxc                     # a container (or a fitted anchor PLY)
    python benchmarks/feature_query.py scene.pxc --points 20000 --xi 0.1,0.25,0.5,0.75,1.0 --seed 0

1. ``--points`` query points drawn uniformly (seeded) in the axis-aligned bounds of the scene's anchors;
2. their features at each resolution ratio xi: ``proxycodec.query_features`` (nearest proxies + residual predictor,
   then the FiLM resolution embedding at xi; the prediction is made once, the embedding per xi);
3. K-means (``--k``, default 3; Lloyd's algorithm from k-means++ seeds, best of ``--n-init`` starts, numpy, seeded)
   of the features at each xi separately;
4. how the assignment shifts with xi: cluster labels are matched between two resolutions by the permutation that
   agrees on the most points, and the fraction of points whose (matched) cluster differs is reported for
   xi = 0.1 -> 1.0 (the headline), for consecutive resolutions and for each xi against 1.0;
5. a PNG: per xi, the points in a 2D PCA projection of the features (one projection for all panels, fitted on the
   features of every xi together, so the panels share axes), coloured by cluster (labels matched to the last xi's).

Outputs in ``--out`` (default ``benchmarks/results/feature_query``): ``feature_query.json`` (every figure, machine,
versions, seed, timings), ``feature_query.png``, ``feature_query_labels.npz`` (the labels per xi, as computed
before matching) and ``feature_query.md``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_XI = (0.1, 0.25, 0.5, 0.75, 1.0)


def kmeans(x: np.ndarray, k: int, rng: np.random.Generator, n_init: int = 10, iters: int = 300
           ) -> tuple[np.ndarray, np.ndarray, float]:
    """(labels [N], centres [k, D], inertia) of the best of ``n_init`` k-means++-seeded Lloyd runs (float64)."""
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    if n < k:
        raise ValueError(f"k-means needs at least k={k} points, got {n}")
    best = None
    for _ in range(n_init):
        centres = [x[rng.integers(n)]]
        d2 = ((x - centres[0]) ** 2).sum(1)
        for _ in range(1, k):
            p = d2 / d2.sum() if d2.sum() > 0 else np.full(n, 1.0 / n)
            centres.append(x[rng.choice(n, p=p)])
            d2 = np.minimum(d2, ((x - centres[-1]) ** 2).sum(1))
        c = np.stack(centres)
        labels = np.full(n, -1)
        for _ in range(iters):
            dist = ((x[:, None, :] - c[None]) ** 2).sum(-1)
            new = dist.argmin(1)
            if np.array_equal(new, labels):
                break
            labels = new
            for j in range(k):
                members = x[labels == j]
                c[j] = members.mean(0) if len(members) else x[dist.min(1).argmax()]  # refill an empty cluster
        inertia = float(((x - c[labels]) ** 2).sum())
        if best is None or inertia < best[2] - 1e-12 * abs(best[2]):
            best = (labels.copy(), c.copy(), inertia)
    return best


def match_labels(ref: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """``labels`` renamed by the permutation of 0..k-1 that agrees with ``ref`` on the most points (first such
    permutation in lexicographic order on ties)."""
    counts = np.zeros((k, k), dtype=np.int64)
    np.add.at(counts, (labels, ref), 1)
    perm = max(itertools.permutations(range(k)), key=lambda p: sum(counts[i, p[i]] for i in range(k)))
    return np.asarray(perm)[labels]


def pca(x: np.ndarray, n: int = 2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(mean, components [n, D] (sign: largest |entry| positive), explained variance ratios [n]) of ``x``."""
    x = np.asarray(x, dtype=np.float64)
    mean = x.mean(0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    comps = vt[:n] * np.sign(vt[:n][np.arange(n), np.abs(vt[:n]).argmax(1)])[:, None]
    var = s ** 2
    return mean, comps, var[:n] / var.sum() if var.sum() > 0 else np.zeros(n)


def _key(xi: float) -> str:
    return f"{xi:g}"


def change(a: np.ndarray, b: np.ndarray, k: int) -> dict:
    m = match_labels(a, b, k)
    n = int((a != m).sum())
    return {"points_changed": n, "fraction_changed": n / len(a)}


def plot(path: Path, proj: dict[float, np.ndarray], labels: dict[float, np.ndarray], changed: np.ndarray | None,
         title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from proxycodec.fileio import atomic_write

    xs = list(proj)
    fig, axes = plt.subplots(1, len(xs), figsize=(3.4 * len(xs), 3.6), dpi=120, squeeze=False)
    allp = np.concatenate(list(proj.values()))
    lo, hi = allp.min(0), allp.max(0)
    pad = 0.04 * (hi - lo + 1e-12)
    colors = np.array(["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink",
                       "tab:gray", "tab:olive", "tab:cyan"])
    for ax, xi in zip(axes[0], xs):
        p, lab = proj[xi], labels[xi]
        ax.scatter(p[:, 0], p[:, 1], s=2, c=colors[lab % len(colors)], linewidths=0, rasterized=True)
        if changed is not None and xi in (xs[0], xs[-1]):
            ax.scatter(p[changed, 0], p[changed, 1], s=6, facecolors="none", edgecolors="k", linewidths=0.3)
        ax.set_xlim(lo[0] - pad[0], hi[0] + pad[0])
        ax.set_ylim(lo[1] - pad[1], hi[1] + pad[1])
        ax.set_title(f"xi = {xi:g}", fontsize=9)
        ax.set_xlabel("PC 1", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("PC 2", fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    with atomic_write(path) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", help="A scene container (.pxc) or an anchor PLY with a stage-2 predictor.")
    ap.add_argument("-o", "--out", default=None, help="Results folder [default: benchmarks/results/feature_query].")
    ap.add_argument("--points", type=int, default=20000, help="Random query points [default: 20000].")
    ap.add_argument("--xi", default=",".join(f"{x:g}" for x in DEFAULT_XI), help="Resolution ratios, comma-separated.")
    ap.add_argument("--k", type=int, default=3, help="K-means clusters [default: 3].")
    ap.add_argument("--n-init", type=int, default=10, help="K-means starts per resolution [default: 10].")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=None, help="torch threads [default: PROXYCODEC_THREADS or cores].")
    args = ap.parse_args(argv)
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from proxycodec.bench import machine_info, versions
    from proxycodec.fileio import atomic_write
    from proxycodec.nearest import nearest_proxy
    from proxycodec.query import FeatureField
    from proxycodec.threads import set_threads

    threads = set_threads(args.threads)
    xis = sorted({float(x) for x in args.xi.split(",") if x.strip()})
    if args.points < args.k or args.k < 1 or not xis:
        ap.error("need --points >= --k >= 1 and at least one xi")
    out = Path(args.out) if args.out else REPO / "benchmarks" / "results" / "feature_query"
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    field = FeatureField.open(args.source)
    t_open = time.perf_counter() - t0
    pos = field.proxy_positions.numpy()
    lo, hi = field.bounds  # of all the anchors, leaves included
    rng = np.random.default_rng(args.seed)
    points = rng.uniform(lo, hi, (args.points, 3)).astype(np.float32)
    t1 = time.perf_counter()
    raw = field.predict(points)
    t_predict = time.perf_counter() - t1
    near = nearest_proxy(np.concatenate([pos, points]), np.arange(len(pos) + len(points)) < len(pos))[len(pos):]
    nearest = np.linalg.norm(points.astype(np.float64) - pos[near], axis=1) / field.voxel_size
    feats, labels, per_xi, t_embed, t_kmeans = {}, {}, [], 0.0, 0.0
    for xi in xis:
        t2 = time.perf_counter()
        feats[xi] = field.embed(points, raw, xi)
        t_embed += time.perf_counter() - t2
        t2 = time.perf_counter()
        lab, centres, inertia = kmeans(feats[xi], args.k, np.random.default_rng([args.seed, int(round(xi * 1e6))]),
                                       args.n_init)
        t_kmeans += time.perf_counter() - t2
        labels[xi] = lab
        _, _, explained = pca(feats[xi])
        per_xi.append({"xi": xi, "cluster_sizes": np.bincount(lab, minlength=args.k).tolist(), "inertia": inertia,
                       "pca_explained": explained.tolist(),
                       "feature_norm_mean": float(np.linalg.norm(feats[xi], axis=1).mean()),
                       "mean_abs_change_vs_unembedded": float(np.abs(feats[xi] - raw).mean())})
    ref = xis[-1]
    changes = {}
    for a, b in zip(xis, xis[1:]):
        changes[f"{_key(a)}->{_key(b)}"] = change(labels[a], labels[b], args.k)
    for a in xis[:-1]:
        changes.setdefault(f"{_key(a)}->{_key(ref)}", change(labels[a], labels[ref], args.k))
    for xi, r in zip(xis, per_xi):  # cluster sizes in the reference's label order, for the table and the plot
        r["cluster_sizes_matched_to_ref"] = np.bincount(match_labels(labels[ref], labels[xi], args.k),
                                                        minlength=args.k).tolist()
    headline = changes.get("0.1->1", {}).get("fraction_changed")
    changed = None
    if 0.1 in labels and 1.0 in labels:
        changed = labels[0.1] != match_labels(labels[0.1], labels[1.0], args.k)
    mean, comps, explained_all = pca(np.concatenate([feats[x] for x in xis]))
    proj = {xi: (feats[xi] - mean) @ comps.T for xi in xis}
    shown = {xi: match_labels(labels[ref], labels[xi], args.k) for xi in xis}
    title = (f"{Path(args.source).name}: {args.points} random points, K-means K={args.k} per xi, PCA of all xi"
             + (f"; {100 * headline:.1f}% change cluster 0.1 -> 1.0 (circled)" if headline is not None else ""))
    plot(out / "feature_query.png", proj, shown, changed, title)
    np.savez(out / "feature_query_labels.npz", **{f"xi_{_key(x)}": labels[x] for x in xis}, points=points)
    res = {
        "kind": "proxycodec.feature_query", "source": str(Path(args.source).resolve()), "points": args.points,
        "k": args.k, "n_init": args.n_init, "seed": args.seed, "xi": xis, "bounds": [lo.tolist(), hi.tolist()],
        "proxies": int(len(pos)), "feat_dim": field.feat_dim,
        "predictor_context": int(getattr(field.predictor.config, "context", 1)),
        "nearest_proxy_distance_voxels": {"mean": float(nearest.mean()), "median": float(np.median(nearest)),
                                          "max": float(nearest.max())},
        "fraction_changed_0.1_to_1.0": headline, "changes": changes, "per_xi": per_xi,
        "pca_all_xi_explained": explained_all.tolist(),
        "seconds": {"open": t_open, "predict": t_predict, "embed": t_embed, "kmeans": t_kmeans,
                    "total": time.perf_counter() - t0},
        "threads": threads, "machine": machine_info(), "versions": versions(),
        "outputs": {"png": "feature_query.png", "labels": "feature_query_labels.npz", "markdown": "feature_query.md"},
    }
    with atomic_write(out / "feature_query.json", "w") as fh:
        json.dump(res, fh, indent=2)
    md = [f"# Feature queries: {Path(args.source).name}", "",
          f"{args.points} points uniform in the anchors' bounds (seed {args.seed}), K-means K={args.k} per xi "
          f"(best of {args.n_init} starts). Fraction of points whose cluster changes between xi = 0.1 and 1.0: "
          + ("n/a (both must be among --xi)" if headline is None else f"**{100 * headline:.2f}%**") + ".", "",
          "| xi | cluster sizes (matched to xi = " + _key(ref) + ") | inertia | PCA explained (2) | mean feature norm "
          "| mean abs change vs unembedded |", "|---:|---|---:|---|---:|---:|"]
    md += [f"| {r['xi']:g} | {r['cluster_sizes_matched_to_ref']} | {r['inertia']:.4g} | "
           f"{', '.join(f'{v:.3f}' for v in r['pca_explained'])} | {r['feature_norm_mean']:.4f} | "
           f"{r['mean_abs_change_vs_unembedded']:.4f} |" for r in per_xi]
    md += ["", "| change | points | fraction |", "|---|---:|---:|"]
    md += [f"| {k} | {v['points_changed']} | {100 * v['fraction_changed']:.2f}% |" for k, v in changes.items()]
    with atomic_write(out / "feature_query.md", "w") as fh:
        fh.write("\n".join(md) + "\n")
    print("\n".join(md))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
