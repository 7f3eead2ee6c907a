"""How the driver stops when it is told to: SIGINT (Ctrl-C) and SIGTERM (``kill``, ``timeout``, a
scheduler preempting the job).

Python turns SIGINT into :class:`KeyboardInterrupt`; inside :func:`sigterm_raises` SIGTERM raises
:class:`Terminated`, a KeyboardInterrupt too, so both unwind the same way: every ``finally`` and
``with`` on the way runs. A table run stops its worker processes, removes the executor's private
temporary folder (:class:`benchmark.run.backends.ProcessBackend`), keeps every unit already stored and
releases the ``--out`` lock; :func:`benchmark.cli.main` then prints one line and exits 130 (SIGINT)
or 143 (SIGTERM, 128 + 15). A rerun with the same command resumes from the stored units.

A second SIGTERM while the first one unwinds is ignored, so it cannot cut the cleanup short; so is
a second Ctrl-C within :data:`SIGINT_GRACE_S` of the first (:func:`sigint_once`: users press it
again when the stop takes a second), and ``python -m benchmark`` ignores both once it has printed
its stop line, while the interpreter exits. The handler is a Python function: a worker started with ``spawn`` does not inherit it (an ``exec``
resets handled signals), so no worker ever runs the driver's cleanup.
"""

from __future__ import annotations

import signal
import threading
import time
from contextlib import contextmanager

__all__ = ["EXIT_SIGINT", "EXIT_SIGTERM", "Terminated", "add_stop_note", "exit_code", "is_terminated_handler",
           "sigint_once", "sigterm_raises", "stop_message"]

EXIT_SIGINT = 128 + signal.SIGINT  # 130, what a shell reports for a process killed by Ctrl-C
EXIT_SIGTERM = 128 + signal.SIGTERM  # 143

_raised = [False]  # a SIGTERM is being handled (reset by each sigterm_raises)


class Terminated(KeyboardInterrupt):
    """The process received SIGTERM (raised in the main thread by :func:`sigterm_raises`' handler).

    A KeyboardInterrupt, so that code which cleans up on Ctrl-C cleans up on SIGTERM as well, and
    ``except Exception`` (a unit that failed) never swallows it."""

    def __init__(self, signum: int = signal.SIGTERM):
        super().__init__(f"received signal {signum} (SIGTERM)")
        self.signum = signum


def _raise_terminated(signum, frame) -> None:
    if _raised[0]:
        return  # already unwinding from the first one
    _raised[0] = True
    raise Terminated(signum)


def is_terminated_handler(handler) -> bool:
    """Whether ``handler`` (``signal.getsignal(SIGTERM)``) is the one :func:`sigterm_raises` installs
    (Ray's ``init`` replaces it; :class:`benchmark.run.backends.RayBackend` puts it back)."""
    return handler is _raise_terminated


@contextmanager
def sigterm_raises():
    """Within the block, SIGTERM raises :class:`Terminated` in the main thread; the previous handler
    comes back afterwards. Does nothing outside the main thread (only it can set handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    _raised[0] = False
    signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    except KeyboardInterrupt as exc:
        if not _raised[0] or isinstance(exc, Terminated):
            raise
        # the handler ran, but what arrives is a new KeyboardInterrupt: Ray's ray.wait / ray.get turn
        # any exception of a signal handler into one. It is still SIGTERM.
        terminated = Terminated()
        if getattr(exc, "stop_note", None):
            terminated.stop_note = exc.stop_note
        raise terminated.with_traceback(exc.__traceback__) from None
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
        _raised[0] = False


SIGINT_GRACE_S = 15.0  # a Ctrl-C this soon after the first one is ignored: the run is stopping already
_interrupted = [None]  # time.monotonic() of the Ctrl-C being handled (reset by each sigint_once)


def _raise_interrupt(signum, frame) -> None:
    first = _interrupted[0]
    if first is not None and time.monotonic() - first < SIGINT_GRACE_S:
        return  # the first one is unwinding: stopping workers, removing files, releasing --out
    _interrupted[0] = time.monotonic()
    raise KeyboardInterrupt


@contextmanager
def sigint_once():
    """Within the block, Ctrl-C raises KeyboardInterrupt as usual, but a second one within
    :data:`SIGINT_GRACE_S` seconds is ignored, so that pressing it again cannot cut the first one's
    cleanup short (workers left running, the executor's folder or the ``--out`` lock left behind, a
    traceback printed). Later, it raises again (should code have swallowed the first). Does nothing
    outside the main thread or where SIGINT is not Python's default handler (ignored, or replaced)."""
    if (threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is not signal.default_int_handler):
        yield
        return
    _interrupted[0] = None
    signal.signal(signal.SIGINT, _raise_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        _interrupted[0] = None


def exit_code(exc: BaseException) -> int:
    """The exit status for an interrupt: 143 after SIGTERM (:class:`Terminated`), 130 after Ctrl-C."""
    return EXIT_SIGTERM if isinstance(exc, Terminated) else EXIT_SIGINT


def add_stop_note(exc: BaseException, note: str) -> None:
    """Attach what was kept (e.g. how many work units are stored, how to resume) to an interrupt on
    its way to :func:`stop_message`. The first note wins: the innermost code knows the most."""
    if not getattr(exc, "stop_note", None):
        try:
            exc.stop_note = note
        except AttributeError:
            pass


def stop_message(exc: BaseException) -> str:
    """The one line :func:`benchmark.cli.main` prints for an interrupt: ``interrupted`` (SIGINT) or
    ``terminated (SIGTERM)``, then its note when one was attached."""
    head = "terminated (SIGTERM)" if isinstance(exc, Terminated) else "interrupted"
    note = getattr(exc, "stop_note", None)
    return f"{head}: {note}" if note else head
