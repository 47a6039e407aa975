"""Our exports read by code that is not ours: PlayCanvas splat-transform (SPZ -> PLY; a LOD set -> Streamed SOG)
and the Khronos gltf-validator (GLB). Each test skips with the reason when Node.js or the npm registry is absent."""

import json

import numpy as np
import pytest

from proxycodec.bench import node_tools
from proxycodec.export import BakeConfig, bake, write_gaussians, write_lod
from proxycodec.formats.inria_ply import read_inria_ply
from proxycodec.formats.spz import read_spz
from tests.test_codec import tiny_model


@pytest.fixture(scope="module")
def splat_transform():
    why = node_tools.splat_transform_unavailable()
    if why:
        pytest.skip(why)
    return node_tools.splat_transform


@pytest.fixture(scope="module")
def decoded():
    m = tiny_model(150)
    return m, bake(m, BakeConfig(xi=0.5, sh_degree=1, directions=4)).ply


def test_splat_transform_reads_our_spz_export_back(tmp_path, splat_transform, decoded):
    _, ply = decoded
    write_gaussians(tmp_path / "e.spz", ply)
    r = splat_transform("-w", tmp_path / "e.spz", tmp_path / "back.ply")
    assert r.returncode == 0, r.stdout + r.stderr
    theirs, (ours, _) = read_inria_ply(tmp_path / "back.ply"), read_spz(tmp_path / "e.spz")
    assert theirs.n_gaussians == ours.n_gaussians == ply.n_gaussians
    assert theirs.means.tobytes() == ours.means.tobytes()
    np.testing.assert_allclose(theirs.sh, ours.sh, atol=1e-6)


def test_a_lod_set_becomes_a_streamed_sog(tmp_path, splat_transform):
    """Our levels, tagged -l 0..n, are what splat-transform builds a PlayCanvas Streamed SOG from (SH degree 0:
    its SOG writer needs a GPU device for higher SH)."""
    m = tiny_model(150)
    man = write_lod(m, tmp_path / "lod", (1.0, 0.25, 0.05), fmt="spz", sh_degree=0, directions=4)
    args = []
    for e in man["levels"]:
        args += [tmp_path / "lod" / e["file"], "-l", e["lod"]]
    r = splat_transform("-w", *args, tmp_path / "sog" / "lod-meta.json")
    assert r.returncode == 0, r.stdout + r.stderr
    meta = json.loads((tmp_path / "sog" / "lod-meta.json").read_text())
    assert meta["counts"] == man["counts"] and meta["lodLevels"] == man["lodLevels"]


def test_gltf_validator_finds_only_the_extension_attribute_names(tmp_path, decoded):
    pkg, why = node_tools.gltf_validator()
    if pkg is None:
        pytest.skip(why)
    _, ply = decoded
    write_gaussians(tmp_path / "e.glb", ply)
    report = node_tools.validate_glb(pkg, tmp_path / "e.glb")
    known, other = node_tools.known_extension_errors(report)
    # one per extension attribute: ROTATION, SCALE, OPACITY and the 4 SH coefficients of degree <= 1
    assert other == [] and len(known) == 3 + 4 and report["issues"]["numWarnings"] == 0
    assert report["info"]["totalVertexCount"] == ply.n_gaussians
