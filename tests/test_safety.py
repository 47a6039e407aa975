"""No code execution from data, and nothing half-written."""

import os
import pickle
import re
import subprocess
import sys
from pathlib import Path

import pytest

from proxycodec.fileio import atomic_write

ROOT = Path(__file__).resolve().parents[1]


class _Boom:
    """Unpickling this creates a marker file: proof that a pickle was executed."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_malicious_pickles_beside_a_scene_are_never_executed(tmp_path):
    marker = tmp_path / "PWNED"
    evil = pickle.dumps(_Boom(str(marker)))
    r = subprocess.run([sys.executable, "-c", "from proxycodec.cli.main import main; main()", "sample",
                        str(tmp_path / "s.ply")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    # Scaffold-GS keeps its MLPs as pickled/TorchScript .pt files beside the PLY: they must be ignored ...
    for name in ("mlp_opacity.pt", "mlp_cov.pt", "mlp_color.pt", "opacity_mlp.pt", "cov_mlp.pt", "color_mlp.pt"):
        (tmp_path / name).write_bytes(evil)
    # ... and a pickle where our weights sidecar should be must be refused, not loaded.
    evil_scene = tmp_path / "evil.ply"
    evil_scene.write_bytes((tmp_path / "s.ply").read_bytes())
    (tmp_path / "evil.weights.pxc").write_bytes(evil)
    ok = subprocess.run([sys.executable, "-c", "from proxycodec.cli.main import main; main()", "render",
                         str(tmp_path / "s.ply"), "--res", "0.05", "--view", "0", "-o", str(tmp_path / "r")],
                        capture_output=True, text=True)
    bad = subprocess.run([sys.executable, "-c", "from proxycodec.cli.main import main; main()", "render",
                          str(evil_scene), "--res", "0.05", "-o", str(tmp_path / "r2")], capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert bad.returncode == 2 and "magic" in bad.stderr and "Traceback" not in bad.stderr
    assert not marker.exists()


def test_no_unpickling_or_eval_in_the_source():
    """No unrestricted unpickling and no eval anywhere: ``torch.load`` only with ``weights_only=True`` (Scaffold-GS's
    ``checkpoints.pth``), and an unpickler only as a subclass whose ``find_class`` allows what it names."""
    import ast

    pattern = re.compile(r"pickle\.loads?\(|torch\.load\((?![^)]*weights_only\s*=\s*True)|allow_pickle\s*=\s*True|"
                         r"(?<![.\w])eval\(|(?<![.\w])exec\(|weights_only\s*=\s*False")
    offenders = []
    for folder in ("proxycodec", "formats", "cli"):
        for p in (ROOT / folder).rglob("*.py"):
            text = p.read_text()
            for i, line in enumerate(text.splitlines(), 1):
                if pattern.search(line.split("#")[0]):
                    offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, ast.ClassDef) and any("Unpickler" in ast.unparse(b) for b in node.bases):
                    methods = {n.name for n in node.body if isinstance(n, ast.FunctionDef)}
                    if "find_class" not in methods:
                        offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}: unpickler {node.name} without find_class")
    assert not offenders, offenders
    assert pattern.search("torch.load(path)") and not pattern.search("torch.load(p, weights_only=True)")


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    for exc in (RuntimeError("boom"), KeyboardInterrupt()):
        with pytest.raises(type(exc)):
            with atomic_write(target) as fh:
                fh.write(b"partial data")
                raise exc
        assert target.read_bytes() == b"old"
        assert sorted(os.listdir(tmp_path)) == ["out.bin"]
    with atomic_write(target) as fh:
        fh.write(b"new")
    assert target.read_bytes() == b"new" and sorted(os.listdir(tmp_path)) == ["out.bin"]


def test_atomic_write_gives_the_usual_file_mode(tmp_path):
    with atomic_write(tmp_path / "f") as fh:
        fh.write(b"x")
    mask = os.umask(0)
    os.umask(mask)
    assert (tmp_path / "f").stat().st_mode & 0o777 == 0o666 & ~mask
