"""Regenerate the golden scene containers: ``python tests/golden/make_golden.py [NAME ...]`` (then commit them and
``hashes.json``; ``tests/test_entropy.py`` decodes them). Names given: only those files are (re)written, the others
and their hashes stay as committed.

One tiny fixed scene (``tiny_model(n=96)`` of ``tests/test_codec.py``), encoded three ways:
- ``scene_v1.pxc``: scene format 1 (one section per weight tensor), zstd;
- ``scene_v2.pxc``: scene format 2 (packed weights), zstd;
- ``scene_v4.pxc``: scene format 4 (attributes arithmetic-coded under the entropy model);
- ``scene_v5.pxc``: scene format 5: the same scene with fixed learned grids and per-cell quantisation levels
  (``golden_steps``), entropy-coded;
- ``scene_v6.pxc``: scene format 6: ``scene_v4.pxc`` with its positions octree-coded (the same symbols otherwise).
``hashes.json`` holds the SHA-256 of the stored arrays each decodes to (``stored_digest``): integer and IEEE
arithmetic only, so they must match on every machine. Regenerating may give other bytes (the entropy model's fit
is float training); the committed files are the reference.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from test_entropy import GOLDEN_KNOBS, golden_scene, golden_scene_levels, stored_digest  # noqa: E402

import numpy as np  # noqa: E402

from proxycodec import codec, entropy, octree  # noqa: E402
from proxycodec.formats.container import read_container, write_container  # noqa: E402
from proxycodec.sections import GRID, read_scene_container  # noqa: E402


NAMES = ("scene_v1.pxc", "scene_v2.pxc", "scene_v4.pxc", "scene_v5.pxc", "scene_v6.pxc")


def main(names=NAMES) -> None:
    model = golden_scene()
    if "scene_v2.pxc" in names:
        codec.encode(model, HERE / "scene_v2.pxc", **GOLDEN_KNOBS, entropy="zstd")
    if "scene_v4.pxc" in names:
        codec.encode(model, HERE / "scene_v4.pxc", **GOLDEN_KNOBS, entropy="model")
    if "scene_v6.pxc" in names:  # the committed format-4 file, its grid deltas replaced by the octree
        c = read_container(HERE / "scene_v4.pxc")
        rel = np.cumsum(c.arrays[GRID].astype(np.int64), axis=1).T
        secs, depth = octree.encode(rel)
        arrays = {**{k: v for k, v in c.arrays.items() if k != GRID}, **secs}
        meta = {**c.meta, "scene_format": 6, "features": ["entropy", "octree"],
                "positions": {**c.meta["positions"], "coding": "octree", "depth": depth, "coder": octree.CODER}}
        write_container(HERE / "scene_v6.pxc", meta, arrays, level=19,
                        raw_sections=frozenset({entropy.STREAM, octree.STREAM}))
    if "scene_v5.pxc" in names:
        codec.encode(golden_scene_levels(), HERE / "scene_v5.pxc", **GOLDEN_KNOBS, entropy="model")
    if "scene_v1.pxc" in names:
        c = read_scene_container(HERE / "scene_v2.pxc")  # format 1: the same arrays, one section per tensor
        meta = {k: v for k, v in c.meta.items() if k != "weights_layout"} | {"scene_format": 1}
        write_container(HERE / "scene_v1.pxc", meta, c.arrays, level=19)
    path = HERE / "hashes.json"
    hashes = json.loads(path.read_text()) if path.exists() else {}
    hashes.update({name: stored_digest(HERE / name) for name in names})
    hashes["tables"] = hashlib.sha256(entropy.scale_tables().tobytes()).hexdigest()
    (HERE / "hashes.json").write_text(json.dumps(hashes, indent=1) + "\n")
    print(json.dumps(hashes, indent=1))


if __name__ == "__main__":
    main(tuple(sys.argv[1:]) or NAMES)
