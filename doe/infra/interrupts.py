"""Ctrl-C and SIGTERM, remembered as well as raised.

A signal's exception can be lost on its way up: nlopt turns one raised at the
edge of its objective into an ordinary stop, and matplotlib drops one raised in
a weakref callback or turns it into a ValueError. The command line therefore
records every signal it receives; a command asked to stop then stops, exits
130 or 143 and publishes nothing, whatever swallowed the exception.
"""

import contextlib
import signal


class Terminated(KeyboardInterrupt):
    """SIGTERM (timeout, CI, a job scheduler), unwound as Ctrl-C is."""


_received = []  # signal numbers received while the handlers were installed
_deferring = [0]  # > 0 inside deferred(): the signal is recorded, raised at its end


def _handler(signum, frame):
    _received.append(signum)
    if not _deferring[0]:
        raise _exception(signum)


def _exception(signum):
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


@contextlib.contextmanager
def handled():
    """Install the SIGINT and SIGTERM handlers for a block; give the caller's back after.

    Only the main thread may set handlers; elsewhere the block runs without them.
    """
    try:
        previous = {s: signal.signal(s, _handler) for s in (signal.SIGINT, signal.SIGTERM)}
    except ValueError:
        previous = {}
    outermost = bool(previous) and all(h is not _handler for h in previous.values())
    if outermost:  # a command run by another (doefab run's stages) shares its record
        _received.clear()
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        if outermost:
            _received.clear()


def check():
    """Raise the interrupt of a signal whose exception something swallowed."""
    if _received:
        raise _exception(_received[-1])


@contextlib.contextmanager
def deferred():
    """Hold a signal's exception back until a block that must not stop half-way is done.

    For moving a finished package into place: stopped there, it would be half
    old and half new, or a lab's files would sit in a folder about to be removed.
    """
    _deferring[0] += 1
    try:
        yield
    finally:
        _deferring[0] -= 1
    if not _deferring[0]:
        check()
