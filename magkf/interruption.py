"""Stopping on a signal: SIGINT, SIGTERM and SIGHUP all stop the ``magkf`` command the same way, by raising
``Interrupted`` (a ``KeyboardInterrupt``) in the main thread, so that every ``finally`` and ``with`` on the
way out runs and removes what the command had begun to write (``magkf.files``).

A signal that arrives while ``held()`` is active (moving outputs into place, removing temporaries) waits
for the block to end; one that arrives while the command is already stopping is ignored, so that a second
Ctrl-C or a SIGTERM after a SIGHUP cannot cut the clean-up short; the ``FORCE``-th raises ``Interrupted`` again
(a clean-up that hangs, or a stop that something swallowed, can still be cut). SIGKILL cannot be caught: what it
leaves is removed by the next run (``magkf.files``).
"""

from __future__ import annotations

import signal
from contextlib import contextmanager

__all__ = ["Interrupted", "SIGNALS", "stop_on_signals", "restore", "held", "stopping", "exit_status"]

#: The signals that stop a command cleanly (those the platform has).
SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name))


class Interrupted(KeyboardInterrupt):
    """The command was stopped by the signal ``signum``."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


_holding = 0  # depth of held() blocks
_pending: int | None = None  # a signal that arrived within held()
_stopping = False  # an Interrupted has been raised
_stopped_by: int | None = None  # the signal it was raised for
_ignored = 0  # signals ignored while stopping
#: The signal, counting the first, that stops a command even while it is stopping (the third Ctrl-C).
FORCE = 3


def _handler(signum, frame) -> None:
    global _pending, _stopping, _ignored, _stopped_by
    if _stopping:
        _ignored += 1
        if _ignored + 1 >= FORCE:
            _ignored = 0
            raise Interrupted(signum)
        return
    if _holding:
        _pending = _pending or signum
        return
    _stopping, _stopped_by = True, signum
    raise Interrupted(signum)


def stop_on_signals() -> dict:
    """Make SIGINT, SIGTERM and SIGHUP raise ``Interrupted`` (call from the main thread); returns the
    handlers they had, for ``restore``."""
    global _pending, _stopping, _ignored, _stopped_by
    _pending, _stopping, _ignored, _stopped_by = None, False, 0, None
    return {signum: signal.signal(signum, _handler) for signum in SIGNALS}


def restore(handlers: dict) -> None:
    """Put back the signal ``handlers`` that ``stop_on_signals`` returned."""
    for signum, handler in handlers.items():
        signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


@contextmanager
def held():
    """Within the block, a stopping signal waits: ``Interrupted`` is raised when the block ends (unless the
    command is stopping already). Blocks may nest."""
    global _holding, _pending, _stopping, _stopped_by
    _holding += 1
    try:
        yield
    finally:
        _holding -= 1
    if not _holding and _pending is not None and not _stopping:
        signum, _pending = _pending, None
        _stopping, _stopped_by = True, signum
        raise Interrupted(signum)


def stopping() -> Interrupted | None:
    """The stop under way (an ``Interrupted`` of the signal that began it), or None. An error that the stop's
    unwinding raised in place of ``Interrupted`` is the stop's: a signal that arrives while an extension module
    initialises (a command's imports) comes out of the import as ``ImportError: initialization failed``."""
    return Interrupted(_stopped_by) if _stopping and _stopped_by is not None else None


def exit_status(exc: KeyboardInterrupt) -> int:
    """The exit status of a command stopped by ``exc``: 128 + the signal's number (130 for Ctrl-C)."""
    return 128 + getattr(exc, "signum", signal.SIGINT)
