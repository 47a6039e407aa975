"""Signals and child processes: SIGTERM as an interrupt, and stopping a child so that it keeps its work.

A scheduler, ``kill`` or ``docker stop`` ends a process with SIGTERM. ``stop_on_sigterm`` turns the first one into
``errors.Terminated`` (a ``KeyboardInterrupt``), so whatever keeps work on Ctrl-C keeps it then too: a training run
writes its checkpoint (``loop.run_checkpointed``, under ``signals_ignored``), a file being written keeps its former
content (``fileio.atomic_write``). ``stop_child`` is how a parent (``batch``, the benchmark runner) hands an interrupt
on.
"""

from __future__ import annotations

import contextlib
import signal
import subprocess
import threading

from .errors import Terminated

#: Seconds a child stopped by its parent has to write its checkpoint before it is killed.
CHILD_GRACE = 120.0
#: Seconds a child that the terminal's Ctrl-C reached too gets to stop on its own before it is sent SIGTERM.
CTRL_C_GRACE = 5.0


_sigterm_received = False


def _on_sigterm(signum, frame) -> None:
    """The first SIGTERM stops the process as Ctrl-C does; a second one kills it at once."""
    global _sigterm_received
    _sigterm_received = True
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    raise Terminated


def terminated(interrupt: BaseException) -> bool:
    """Whether ``interrupt`` stands for SIGTERM: ``Terminated``, or any ``KeyboardInterrupt`` once SIGTERM came (a
    library may catch the first and raise a plain one: Ray's ``wait`` does)."""
    return isinstance(interrupt, Terminated) or (isinstance(interrupt, KeyboardInterrupt) and _sigterm_received)


def stop_on_sigterm() -> None:
    """From now on the first SIGTERM raises ``Terminated`` in the main thread (call it from the main thread)."""
    signal.signal(signal.SIGTERM, _on_sigterm)


@contextlib.contextmanager
def _handlers(handlers: dict):
    """Inside the block each signal of ``handlers`` has the handler given (None: left as it is), afterwards the one it
    had before. Main thread only, where Python lets handlers be set; elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    saved = {s: signal.getsignal(s) for s in handlers}
    for s, handler in handlers.items():
        if handler is not None:
            signal.signal(s, handler)
    try:
        yield
    finally:
        for s, handler in saved.items():
            if handler is not None:  # None: a handler not set from Python, which cannot be put back
                signal.signal(s, handler)


def sigterm_kept():
    """SIGTERM's handler as it was before the block, whatever the block installs (Ray's ``init`` installs one that
    aborts the process)."""
    return _handlers({signal.SIGTERM: None})


def signals_ignored():
    """SIGINT and SIGTERM ignored inside the block, then as they were: the checkpoint written on an interrupt is not
    cut short by the next one (a parent's SIGTERM after the terminal's Ctrl-C, a second Ctrl-C)."""
    return _handlers({signal.SIGINT: signal.SIG_IGN, signal.SIGTERM: signal.SIG_IGN})


def _cancel(signum, frame) -> None:
    raise Terminated


def sigint_raises(cancel: bool = False):
    """SIGINT raises ``KeyboardInterrupt`` inside the block even in a process that started with it ignored (any child
    of a background job): Ray cancels a running task by simulating SIGINT in its worker's main thread, which does
    nothing where SIGINT is ignored. ``cancel``: it raises ``Terminated`` instead, for a SIGINT that no terminal sent
    (Ray's cancel): ``stop_child`` then stops a child at once, without the Ctrl-C grace, which waits for a child that
    the terminal's Ctrl-C reached too."""
    return _handlers({signal.SIGINT: _cancel if cancel else signal.default_int_handler})


def stop_child(p: subprocess.Popen, interrupt: BaseException) -> None:
    """Stop child ``p`` because this process got ``interrupt``. After Ctrl-C (a plain ``KeyboardInterrupt``: the
    terminal sent SIGINT to the child as well) it first gets ``CTRL_C_GRACE`` seconds to stop on its own, so that no
    second signal lands while it starts writing its checkpoint; then SIGTERM, and SIGKILL after ``CHILD_GRACE``
    seconds."""
    if isinstance(interrupt, KeyboardInterrupt) and not terminated(interrupt):
        try:
            p.wait(timeout=CTRL_C_GRACE)
            return
        except subprocess.TimeoutExpired:
            pass
    if p.poll() is None:
        p.terminate()
    try:
        p.wait(timeout=CHILD_GRACE)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()
