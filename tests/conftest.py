"""Shared test helpers.

Real public data sit in ``../shared/data`` relative to the repository root (see shared/data/README.md).
Tests that need it use the ``shared_data`` fixture or :func:`shared_data_path`, which skip with a clear
reason when the folder (or the scene) is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# The Ray tests start Ray on this machine alone: on the loopback address, never on the machine's network address
# (Ray reads this when it is imported; proxycodec.batch.local_ray_on_loopback does the same for a local batch).
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def pytest_configure(config) -> None:
    config.addinivalue_line(
        "markers", "cuda: needs a CUDA GPU and gsplat (the cuda backend); skipped with the reason "
                   "proxycodec.devices.cuda_unavailable_reason() gives where they are missing")


def pytest_collection_modifyitems(config, items) -> None:
    """Skip ``cuda``-marked tests where CUDA work cannot run (torch is imported only when such a test exists)."""
    marked = [item for item in items if item.get_closest_marker("cuda") is not None]
    if not marked:
        return
    from proxycodec.devices import cuda_unavailable_reason

    why = cuda_unavailable_reason()
    if why is not None:
        skip = pytest.mark.skip(reason=f"needs CUDA: {why}")
        for item in marked:
            item.add_marker(skip)


def shared_data_path(*parts: str) -> Path:
    """``../shared/data/<parts>``, or skip the calling test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not available: {SHARED_DATA} is absent (see shared/data/README.md)")
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real test data not available: {p} is absent")
    return p


def load_benchmark(name: str):
    """``benchmarks/<name>.py`` as a module (the benchmarks are scripts, not part of the package)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, Path(__file__).parents[1] / "benchmarks" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def shared_data() -> Path:
    """The ``../shared/data`` folder; skips the test when it is absent."""
    return shared_data_path()


@pytest.fixture(scope="module")
def one_thread():
    """Run a module's tiny cases on one thread (torch and numba): on a loaded 2-core machine intra-op threads cost
    far more than they save. Modules opt in with ``pytestmark = pytest.mark.usefixtures("one_thread")``."""
    import numba
    import torch

    old_t, old_n = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(old_t)
    numba.set_num_threads(old_n)


def write_blender(root: Path, splits: dict, render) -> Path:
    """Write a tiny NeRF-Synthetic-style dataset: ``splits`` maps "train"/"test" to cameras (all the same size and
    field of view); ``render(camera)`` returns the [H, W, 3] image in [0, 1] (a torch tensor or numpy array)."""
    import json
    import math

    import numpy as np
    from PIL import Image

    from proxycodec.lite import image_to_uint8

    cams = [c for cs in splits.values() for c in cs]
    fov = 2 * math.atan(0.5 * cams[0].width / cams[0].fx)
    for split, cs in splits.items():
        (root / split).mkdir(parents=True)
        frames = []
        for k, cam in enumerate(cs):
            img = render(cam)
            img = img.detach().cpu().numpy() if hasattr(img, "detach") else np.asarray(img)
            Image.fromarray(image_to_uint8(img)).save(root / split / f"r_{k}.png")
            c2w = np.linalg.inv(cam.world_to_camera)
            c2w[:3, 1:3] *= -1.0  # OpenCV -> OpenGL/Blender axes
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    return root


# ------------------------------------------------------------------------------ hostile PyTorch files
def replace_zip_record(data: bytes, suffix: str, new: bytes) -> bytes:
    """A zip archive (``data``) with the record whose name ends with ``suffix`` replaced by ``new``."""
    import io
    import zipfile

    with zipfile.ZipFile(io.BytesIO(data)) as z:
        items = [(i, z.read(i)) for i in z.infolist()]
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        for info, b in items:
            z.writestr(info, new if info.filename.endswith(suffix) else b)
    return out.getvalue()


def os_system_pickle(command: str) -> bytes:
    """A pickle whose loading calls ``os.system(command)`` (what a restricted unpickler must refuse)."""
    import os
    import pickle

    class Evil:
        def __reduce__(self):
            return os.system, (command,)

    return pickle.dumps(Evil(), protocol=2)


def forged_tensor_pickle(shape, stride, numel: int, key: str = "0") -> bytes:
    """A ``data.pkl`` of ``{"weight": tensor}`` whose tensor is ``_rebuild_tensor_v2`` over storage ``key`` (declared
    ``numel`` float32 elements) with the given (forged) shape and stride, pickled as torch pickles one."""
    import io
    import pickle
    from collections import OrderedDict

    import torch

    class Storage:
        pass

    class Tensor:
        def __reduce__(self):
            return torch._utils._rebuild_tensor_v2, (Storage(), 0, tuple(shape), tuple(stride), False, OrderedDict())

    class Pickler(pickle.Pickler):
        def persistent_id(self, obj):
            return ("storage", torch.FloatStorage, key, "cpu", numel) if isinstance(obj, Storage) else None

    buf = io.BytesIO()
    Pickler(buf, protocol=2).dump({"weight": Tensor()})
    return buf.getvalue()


def write_corner_dataset(root: Path, size: int = 32) -> Path:
    """A tiny Blender dataset of one corner of the built-in scene (the box and part of the floor) rendered from 10
    orbit cameras at ``size`` px, every 5th a test view: what a few dozen ``fit`` iterations can learn."""
    import torch

    from proxycodec.camera import orbit_cameras
    from proxycodec.model import SceneModel
    from proxycodec.sample import sample_model

    m = sample_model()
    s = m.scene
    lo, hi = torch.tensor([0.15, -0.85, -0.05]), torch.tensor([0.95, -0.05, 0.6])
    corner = SceneModel(s.subset(((s.positions >= lo) & (s.positions <= hi)).all(1).nonzero().squeeze(1)), m.decoder)
    cams = orbit_cameras((0.55, -0.45, 0.2), 1.8, 10, elevation_deg=35.0, fov_x_deg=45.0, width=size, height=size)
    splits = {"train": [c for i, c in enumerate(cams) if i % 5 != 0], "test": [c for i, c in enumerate(cams) if i % 5 == 0]}
    return write_blender(root, splits, lambda cam: corner.render(cam, 1.0).image)


def signal_when_ready(p, sig, wait_ready, timeout: float = 120.0) -> tuple[str | None, str | None]:
    """Send ``sig`` to the ``subprocess.Popen`` ``p`` once ``wait_ready()`` has returned (it reads the child's
    output until the moment to signal), then (stdout, stderr) as the child exits. On any failure the child is killed,
    so a test never leaves one running."""
    try:
        wait_ready()
        p.send_signal(sig)
        return p.communicate(timeout=timeout)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate(timeout=30)


def read_until(stream, starts: str) -> list[str]:
    """The lines read from ``stream`` up to and including the first that starts with ``starts``."""
    seen = []
    for line in stream:
        seen.append(line)
        if line.startswith(starts):
            break
    return seen
