"""proxycodec: a compression codec for anchor-based 3D Gaussian Splatting scenes (compact proxy anchors)."""

__version__ = "0.1.0"

from .errors import ProxycodecError  # noqa: E402

__all__ = ["ProxycodecError", "__version__"]
