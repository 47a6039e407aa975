"""The one exception type that user-facing code lets escape."""

from __future__ import annotations

import os


class ProxycodecError(ValueError):
    """Bad input (a file, a parameter) that the user can fix.

    The CLI prints ``str(err)`` on one line and exits non-zero; library users catch this one type.
    ``path`` names the offending file when there is one; it is prefixed to the message.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None):
        self.path = None if path is None else os.fspath(path)
        self.reason = message
        super().__init__(f"{self.path}: {message}" if self.path else message)


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler's stop, ``kill``, ``docker stop``), raised in the main thread by the handler the command
    line installs (``processes.stop_on_sigterm``). It is a ``KeyboardInterrupt``, so everything that keeps work on
    Ctrl-C keeps it here too: a training run writes its checkpoint, a write in progress leaves the old file and no
    temporary."""
