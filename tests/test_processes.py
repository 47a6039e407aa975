"""Signals and child processes (``proxycodec.processes``): SIGTERM as an interrupt, a checkpoint that the next
signal cannot cut short, and a parent that stops its child so that the child keeps its work."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from proxycodec.errors import Terminated
from proxycodec.processes import signals_ignored, sigterm_kept, stop_child, stop_on_sigterm, terminated

#: A child that says "ready", then sleeps; on SIGTERM it writes "term" to the file given and exits 143.
CHILD = """
import signal, sys, time
def on_term(*a):
    open(sys.argv[1], "w").write("term")
    sys.exit(143)
signal.signal(signal.SIGTERM, on_term)
print("ready", flush=True)
time.sleep(float(sys.argv[2]))
"""


def _child(tmp_path, sleep: float) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", CHILD, str(tmp_path / "said"), str(sleep)], stdout=subprocess.PIPE,
                         text=True)
    assert p.stdout.readline() == "ready\n"
    return p


@pytest.fixture(autouse=True)
def sigterm_restored(monkeypatch):
    """Each test starts with no SIGTERM seen and leaves the process's handler as it found it."""
    import proxycodec.processes as processes

    monkeypatch.setattr(processes, "_sigterm_received", False)
    saved = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, saved)


def test_the_first_sigterm_raises_terminated_and_the_second_is_the_default():
    stop_on_sigterm()
    with pytest.raises(Terminated) as e:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler runs at the next bytecode; never reached
    assert isinstance(e.value, KeyboardInterrupt)
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    assert terminated(KeyboardInterrupt())  # what a library re-raises after catching it stands for SIGTERM too


def test_a_plain_keyboard_interrupt_is_ctrl_c_until_sigterm_came():
    assert not terminated(KeyboardInterrupt()) and terminated(Terminated()) and not terminated(ValueError())


def test_signals_are_ignored_inside_the_block_then_handled_as_before():
    stop_on_sigterm()
    before = signal.getsignal(signal.SIGINT)
    with signals_ignored():
        os.kill(os.getpid(), signal.SIGTERM)
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.05)
    assert signal.getsignal(signal.SIGINT) is before and signal.getsignal(signal.SIGTERM) is not signal.SIG_IGN
    with pytest.raises(Terminated):  # the handler is back
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)


def test_a_terminated_parent_stops_its_child_with_sigterm_at_once(tmp_path):
    p = _child(tmp_path, 60)
    t0 = time.monotonic()
    stop_child(p, Terminated())
    assert p.returncode == 143 and (tmp_path / "said").read_text() == "term"
    assert time.monotonic() - t0 < 4  # no Ctrl-C grace: the terminal did not signal the child


def test_after_ctrl_c_a_child_that_stops_on_its_own_gets_no_sigterm(tmp_path):
    p = _child(tmp_path, 1)  # stands for a child that the terminal's Ctrl-C reached too: done within the grace
    stop_child(p, KeyboardInterrupt())
    assert p.returncode == 0 and not (tmp_path / "said").exists()


def test_after_ctrl_c_a_child_still_running_gets_sigterm_after_the_grace(tmp_path, monkeypatch):
    import proxycodec.processes as processes

    monkeypatch.setattr(processes, "CTRL_C_GRACE", 0.5)
    p = _child(tmp_path, 60)
    stop_child(p, KeyboardInterrupt())
    assert p.returncode == 143 and (tmp_path / "said").read_text() == "term"


def test_a_child_that_ignores_sigterm_is_killed_after_the_grace(tmp_path, monkeypatch):
    import proxycodec.processes as processes

    monkeypatch.setattr(processes, "CHILD_GRACE", 0.5)
    code = "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('ready', flush=True); time.sleep(60)"
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline() == "ready\n"
    stop_child(p, Terminated())
    assert p.returncode == -signal.SIGKILL


def test_sigterm_kept_puts_back_the_handler_a_library_replaced():
    stop_on_sigterm()
    ours = signal.getsignal(signal.SIGTERM)
    with sigterm_kept():
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # what ray.init does, with a handler of its own
    assert signal.getsignal(signal.SIGTERM) is ours


def test_sigint_raises_inside_the_block_even_where_it_was_ignored():
    from proxycodec.processes import sigint_raises

    before = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job's child
    try:
        with pytest.raises(KeyboardInterrupt), sigint_raises():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # the handler runs at the next bytecode; never reached
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def test_sigint_as_a_cancel_raises_terminated_and_the_child_gets_sigterm_at_once(monkeypatch):
    """Ray's cancel (a SIGINT no terminal sent): ``Terminated``, so ``stop_child`` skips the Ctrl-C grace."""
    from proxycodec import processes
    from proxycodec.processes import sigint_raises

    monkeypatch.setattr(processes, "CTRL_C_GRACE", 30.0)
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    code = "import time; print('ready', flush=True); time.sleep(60)"
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline() == "ready\n"
        with pytest.raises(Terminated) as e, sigint_raises(cancel=True):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # never reached
        t0 = time.monotonic()
        stop_child(p, e.value)
        assert p.returncode == -signal.SIGTERM and time.monotonic() - t0 < 10  # not after the 30-s grace
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
        if p.poll() is None:
            p.kill()
