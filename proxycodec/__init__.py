"""proxycodec: a compression codec for anchor-based 3D Gaussian Splatting scenes (compact proxy anchors).

The Python API mirrors the CLI::

    import proxycodec
    report = proxycodec.encode("scene.ply", "scene.pxc")       # proxies + predictor + quantisation -> container
    model = proxycodec.decode("scene.pxc")                      # leaves regenerated -> SceneModel
    renders = proxycodec.render("scene.pxc", xi=0.3)            # one RenderResult per stored camera
    info = proxycodec.stats("scene.pxc")                        # what is inside and what it costs
    f = proxycodec.query_features("scene.pxc", points, xi=0.3)  # anchor features at any [N, 3] points

The heavy modules (torch) load on first use, so ``import proxycodec`` and ``proxycodec --help`` stay fast.
"""

__version__ = "0.1.0"

import os as _os

# torch and numba (threading layer "omp") share GNU OpenMP, whose idle threads spin 300k iterations before they
# sleep. On a 2-core machine with anything else running, spinning threads steal the core a worker needs: a D-SSIM
# forward+backward at 400 px took 1264 ms with 2 threads instead of 119 ms with a 1000-iteration spin (SPEC.md 8).
# Only a default: a value the user set wins, and it must be set before torch starts its thread pool.
_os.environ.setdefault("GOMP_SPINCOUNT", "1000")

from .errors import ProxycodecError  # noqa: E402

# Run from a source checkout (``python -m proxycodec.cli`` or ``pytest`` in the repository root, where this folder
# shadows an installed copy): the sub-packages pyproject maps from the sibling folders formats/ and cli/ are found
# there too. An installed package has them inside and is left alone.
_here = _os.path.dirname(__file__)
if not _os.path.isdir(_os.path.join(_here, "formats")) and \
        _os.path.isfile(_os.path.join(_here, _os.pardir, "formats", "__init__.py")):
    __path__.append(_os.path.normpath(_os.path.join(_here, _os.pardir)))  # noqa: F821 (a package's own __path__)

_LAZY = {"encode": "codec", "decode": "codec", "load": "codec", "render": "codec", "stats": "codec",
         "query_features": "query", "FeatureField": "query"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'proxycodec' has no attribute {name!r}")


__all__ = ["FeatureField", "ProxycodecError", "__version__", "encode", "decode", "load", "query_features", "render",
           "stats"]
