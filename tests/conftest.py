"""Shared test helpers.

Real public data sit in ``../shared/data`` relative to the repository root (see shared/data/README.md).
Tests that need it use the ``shared_data`` fixture or :func:`shared_data_path`, which skip with a clear
reason when the folder (or the scene) is absent.
"""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


def shared_data_path(*parts: str) -> Path:
    """``../shared/data/<parts>``, or skip the calling test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real test data not available: {SHARED_DATA} is absent (see shared/data/README.md)")
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real test data not available: {p} is absent")
    return p


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
