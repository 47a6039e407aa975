"""Independent readers from npm, run through Node.js: PlayCanvas splat-transform (via npx) and the Khronos
gltf-validator (installed once into ``$PROXYCODEC_NPM_CACHE``, default ``~/.cache/proxycodec-npm``). Tests and
benchmarks use them to check our files with code that is not ours; each function answers why it cannot run
instead of raising, so a caller can skip with the reason when Node or the registry is absent."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

#: The newest splat-transform that runs on Node 20 (3.x needs Node >= 22).
SPLAT_TRANSFORM = "@playcanvas/splat-transform@2.7.1"
#: The newest gltf-validator on npm.
GLTF_VALIDATOR = "gltf-validator@2.0.0-dev.3.10"

_VALIDATE_JS = """const fs = require('fs');
const validator = require(process.argv[2]);
const buf = fs.readFileSync(process.argv[3]);
validator.validateBytes(new Uint8Array(buf), {maxIssues: 0})
  .then((r) => console.log(JSON.stringify(r)))
  .catch((e) => { console.error(String(e)); process.exit(2); });
"""

_splat_transform_why: list[str | None] = []  # memo: [why not] once asked


def splat_transform_unavailable() -> str | None:
    """None when ``npx splat-transform`` runs here (fetched on first use), else why not."""
    if _splat_transform_why:
        return _splat_transform_why[0]
    why = None
    if shutil.which("npx") is None:
        why = "npx (Node.js) is not installed"
    else:
        try:
            r = subprocess.run(["npx", "-y", SPLAT_TRANSFORM, "--help"], capture_output=True, text=True, timeout=240)
            if r.returncode != 0 or "splat-transform" not in r.stdout:
                why = f"npx could not run {SPLAT_TRANSFORM} (no registry access?): {r.stderr.strip()[-200:]}"
        except subprocess.TimeoutExpired:
            why = f"npx could not fetch {SPLAT_TRANSFORM} in time (no registry access?)"
    _splat_transform_why.append(why)
    return why


def splat_transform(*args, timeout: float = 600) -> subprocess.CompletedProcess:
    """``splat-transform ARGS`` (check ``splat_transform_unavailable`` first)."""
    return subprocess.run(["npx", "-y", SPLAT_TRANSFORM, *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


def npm_cache() -> Path:
    return Path(os.environ.get("PROXYCODEC_NPM_CACHE", Path.home() / ".cache" / "proxycodec-npm"))


def gltf_validator() -> tuple[Path | None, str | None]:
    """(the gltf-validator package folder, None), installing it on first use; or (None, why not)."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        return None, "node/npm (Node.js) is not installed"
    prefix = npm_cache()
    pkg = prefix / "node_modules" / "gltf-validator"
    want = GLTF_VALIDATOR.split("@")[1]
    try:
        have = json.loads((pkg / "package.json").read_text())["version"]
    except (OSError, ValueError, KeyError):
        have = None
    if have != want:
        prefix.mkdir(parents=True, exist_ok=True)
        try:
            r = subprocess.run(["npm", "install", "--prefix", str(prefix), "--no-audit", "--no-fund", GLTF_VALIDATOR],
                               capture_output=True, text=True, timeout=600)
        except subprocess.TimeoutExpired:
            return None, f"npm could not install {GLTF_VALIDATOR} in time (no registry access?)"
        if r.returncode != 0 or not (pkg / "package.json").is_file():
            return None, f"npm could not install {GLTF_VALIDATOR} (no registry access?): {r.stderr.strip()[-200:]}"
    return pkg, None


def validate_glb(pkg: Path, glb: str | os.PathLike) -> dict:
    """gltf-validator's report (its JSON) for the file ``glb``."""
    script = npm_cache() / "proxycodec-validate.js"
    if not script.is_file() or script.read_text() != _VALIDATE_JS:
        script.parent.mkdir(parents=True, exist_ok=True)
        script.write_text(_VALIDATE_JS)
    r = subprocess.run(["node", str(script), str(pkg), str(glb)], capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        raise RuntimeError(f"gltf-validator failed on {glb}: {r.stderr.strip()[-300:]}")
    return json.loads(r.stdout)


def known_extension_errors(report: dict) -> tuple[list[dict], list[dict]]:
    """(errors about the ``KHR_gaussian_splatting:*`` attribute names, every other error) of a validator report.

    gltf-validator 2.0.0-dev.3.10 does not know the extension and still applies the core rule that application
    attribute names start with ``_`` (KhronosGroup/glTF-Validator#252, open; the core change is glTF#2514): it
    flags each extension attribute of any conforming file, splat-transform's included."""
    errors = [m for m in report["issues"]["messages"] if m["severity"] == 0]
    known = [m for m in errors if m["code"] == "MESH_PRIMITIVE_INVALID_ATTRIBUTE"
             and m.get("pointer", "").split("/")[-1].startswith("KHR_gaussian_splatting:")]
    return known, [m for m in errors if m not in known]
