"""Counting the torch operations a piece of code dispatches (``benchmarks/step_ops.py``, and the tests that keep a
training step's operation and synchronisation counts from creeping back up)."""

from __future__ import annotations

import collections
from collections.abc import Callable


def dispatch_counter(on_op: Callable[[str], None] | None = None):
    """A ``TorchDispatchMode`` that counts, by name, every torch operation dispatched inside its ``with`` block
    (backward included): ``.counts`` (a ``collections.Counter``) and ``.names`` (in dispatch order). ``on_op(name)``
    is called for each too. Every dispatched operation is at least one kernel launch on a GPU."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Counter(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.counts: collections.Counter = collections.Counter()
            self.names: list[str] = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            name = func.overloadpacket.__name__
            self.counts[name] += 1
            self.names.append(name)
            if on_op is not None:
                on_op(name)
            return func(*args, **(kwargs or {}))

    return Counter()
