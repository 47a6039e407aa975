"""The number of threads torch's CPU work uses: one setting, applied once per process by its entry point (the
command line, the bench step worker, the benchmark scripts). Library functions never set it themselves."""

from __future__ import annotations

import importlib.abc
import importlib.util
import os
import sys

from .errors import ProxycodecError

#: Environment variable holding the count; :func:`set_threads` sets it too, so child processes inherit the choice.
ENV = "PROXYCODEC_THREADS"

_count: int | None = None


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform reports one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # no sched_getaffinity (macOS, Windows)
        return os.cpu_count() or 1


def set_threads(n: int | None = None) -> int:
    """Use ``n`` threads (None: ``$PROXYCODEC_THREADS``, else :func:`usable_cores`) and return the count.

    A process that has not imported torch yet does not import it here (``decode`` renders without torch): the
    count is applied as soon as torch is first imported."""
    global _count
    if n is None:
        text = os.environ.get(ENV, "").strip()
        try:
            n = int(text) if text else usable_cores()
        except ValueError:
            raise ProxycodecError(f"{ENV} must be a whole number of threads, got {text!r}") from None
    if n < 1:
        raise ProxycodecError(f"the thread count must be >= 1, got {n}")
    _count = n
    os.environ[ENV] = str(n)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(n)
    elif not any(isinstance(f, _ApplyOnTorchImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _ApplyOnTorchImport())
    return n


class _ApplyOnTorchImport(importlib.abc.MetaPathFinder):
    """Finds torch as the other finders do, then sets its thread count once it has been executed; steps aside
    after that first lookup."""

    def find_spec(self, name, path=None, target=None):
        if name != "torch":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.loader is not None:
            exec_module = spec.loader.exec_module

            def exec_then_set_threads(module):
                exec_module(module)
                module.set_num_threads(_count)

            spec.loader.exec_module = exec_then_set_threads
        return spec
