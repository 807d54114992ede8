"""A stop asked for by SIGINT or SIGTERM, kept until the run has stopped.

The signal handler raises `Interrupted` wherever the main thread is. Python swallows an exception raised
inside a finalizer or a weakref callback ("Exception ignored in ..."), so a signal that lands there would be
lost and the run would publish its outputs as if never stopped; the stop is therefore also remembered
(`request`), and the batch asks again (`check`) after every pass and before it publishes.
"""

from __future__ import annotations

import signal

_requested: int | None = None  # the signal of a stop not yet carried out


class Interrupted(BaseException):
    """SIGINT or SIGTERM during a run. A BaseException, as KeyboardInterrupt is: a pass's `except Exception`
    (one pass's failure must not stop the night) must not take a stop for a failed pass (with --jobs 1 the
    passes run in the main thread)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum, self.name = signum, signal.Signals(signum).name


def request(signum: int) -> None:
    """Remember a stop and raise it here (the signal handler's body)."""
    global _requested
    _requested = signum
    raise Interrupted(signum)


def check() -> None:
    """Raise the stop asked for, if any: it may have been swallowed where the handler first raised it."""
    if _requested is not None:
        raise Interrupted(_requested)


def quiet_unraisable(hook):
    """A `sys.unraisablehook` that says nothing of an `Interrupted` swallowed in a finalizer or a weakref
    callback (it is remembered and raised again at the next `check`; printed, it read as a traceback after
    "stopped by SIGTERM") and passes anything else to `hook`."""
    def quiet(unraisable) -> None:
        if not isinstance(unraisable.exc_value, Interrupted):
            hook(unraisable)
    return quiet


def clear() -> None:
    global _requested
    _requested = None
