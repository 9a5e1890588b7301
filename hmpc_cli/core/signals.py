"""Stopping a run on SIGINT, SIGTERM and SIGHUP: a flag, a check, clean ends.

:func:`handle_signals` installs handlers that record the first stop signal. Where a
stop may interrupt the work at once (outside :func:`deferred` sections, or inside an
:func:`abortable` one such as an IPOPT solve) the handler raises :class:`Interrupted`
(a ``KeyboardInterrupt``, as Python does for SIGINT); inside a :func:`deferred` section
(the closed loop's simulator step and logging) it only records the signal, and the code
calls :func:`check` at safe points (after every step, after every solve). CasADi swallows
exceptions raised in IPOPT's callbacks and returns ``NonIpopt_Exception_Thrown``; the
solver session turns that status back into :class:`Interrupted` (:func:`check` after the
solve), and CasADi's warning about it is left out of stderr. Nothing happens at import.

A stop signal the process was started ignoring stays ignored (``nohup``'s SIGHUP, a
background job's SIGINT): :func:`stoppable`.
"""

from __future__ import annotations

import _thread
import contextlib
import signal
import sys
import threading
import time
from collections.abc import Iterator

__all__ = ["EXIT_CODES", "Interrupted", "abortable", "as_interrupted", "check", "deferred",
           "handle_signals", "install_deferred", "pending", "reset", "stoppable"]

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
EXIT_CODES = {int(s): 128 + int(s) for s in STOP_SIGNALS}  # 130, 143, 129


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal.

    Attributes:
        signum: the signal number (SIGINT for a plain Ctrl-C without handlers).
    """

    def __init__(self, signum: int = signal.SIGINT) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = int(signum)

    @property
    def name(self) -> str:
        """The signal's name, e.g. ``SIGTERM``."""
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        """128 + the signal number (130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP)."""
        return 128 + self.signum


class _State:
    """The process's stop state (signal handlers run in the main thread)."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.raise_now = True  # the handler may raise (False inside deferred sections)
        self.installed = False
        self.solving = False  # inside an abortable section (an IPOPT solve)
        self.quiet: _Unreported | None = None  # sys.stderr's filter after a signal in one
        self.dropped: int | None = None  # a raise Python dropped, to be raised again
        self.raised: Interrupted | None = None  # the handler's last raise (not check()'s)
        self.generation = 0  # handle_signals' entries and exits: a late re-raise is stale


_STATE = _State()


def _handler(signum: int, frame) -> None:
    if _STATE.signum is None:
        _STATE.signum = int(signum)
    if _STATE.raise_now:
        _STATE.raise_now = False  # raise once; the code then checks the flag
        _STATE.dropped = None  # raised (again): a drop says so anew
        if _STATE.solving and _STATE.quiet is None:  # inside a solve CasADi catches the
            # interrupt and warns about it: that line is left out of stderr
            _STATE.quiet = sys.stderr = _Unreported(sys.stderr)
        _STATE.raised = Interrupted(_STATE.signum)
        raise _STATE.raised


def as_interrupted(exc: BaseException) -> Interrupted:
    """``exc`` as :class:`Interrupted` (a plain KeyboardInterrupt: the pending signal or SIGINT)."""
    if isinstance(exc, Interrupted):
        return exc
    return Interrupted(_STATE.signum or signal.SIGINT)


def pending() -> int | None:
    """The first stop signal received (None if none)."""
    return _STATE.signum


def reset() -> None:
    """Forgets a received signal (tests, and a fresh run in a long-lived process)."""
    _STATE.signum = _STATE.dropped = None


def check() -> None:
    """Raises :class:`Interrupted` if a stop signal was received.

    Raises:
        Interrupted: a stop signal is pending.
    """
    if _STATE.signum is not None:
        _STATE.dropped = None  # raised here: a dropped raise is not asked for again
        raise Interrupted(_STATE.signum)


@contextlib.contextmanager
def _raising(value: bool) -> Iterator[None]:
    previous = _STATE.raise_now
    _STATE.raise_now = value
    try:
        yield
    finally:
        _STATE.raise_now = previous


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """A section a signal must not cut (logging): the handler only records the signal."""
    with _raising(False):
        yield


class _Unreported:
    """``sys.stderr`` from a stop signal inside a solve to the section's end.

    Forwards whole lines, but CasADi's warning about the interrupt it caught in an IPOPT
    callback (written in pieces; the command reports the stop in its own one line).
    """

    def __init__(self, stream) -> None:
        self._stream = stream
        self._line = ""
        self._lock = threading.Lock()

    def write(self, text: str) -> int:
        with self._lock:
            *lines, self._line = (self._line + text).split("\n")
            for line in lines:
                self._forward(line + "\n")
        return len(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def _forward(self, text: str) -> None:
        if CASADI_INTERRUPT not in text:
            self._stream.write(text)

    def release(self) -> None:
        """Forwards a partial line left (unless CasADi's warning) and flushes.

        A broken stream is left for its next user to find, not made this section's error.
        """
        with self._lock:
            line, self._line = self._line, ""
            with contextlib.suppress(OSError, ValueError):
                if line:
                    self._forward(line)
                self._stream.flush()

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


#: the text of CasADi's warning when a callback of IPOPT raised KeyboardInterrupt
CASADI_INTERRUPT = 'WARNING("KeyboardInterruptException")'


@contextlib.contextmanager
def abortable() -> Iterator[None]:
    """A long computation a signal may cut (an IPOPT solve); checks on entry and exit.

    A stop signal inside it leaves CasADi's warning about the interrupt out of stderr
    (:class:`_Unreported`, from the signal to the end of the outermost section).

    Raises:
        Interrupted: a stop signal is pending, or arrives during the section.
    """
    check()
    outer = _STATE.solving
    try:
        _STATE.solving = True
        with _raising(True):
            yield
    finally:
        _STATE.solving = outer
        if not outer:
            _release_stderr()
    check()


def _release_stderr() -> None:
    """Ends :class:`_Unreported` (if a signal installed it): sys.stderr back, its rest out."""
    quiet, _STATE.quiet = _STATE.quiet, None
    if quiet is None:
        return
    if sys.stderr is quiet:
        sys.stderr = quiet._stream
    quiet.release()


def _unraisable(hook):
    """``sys.unraisablehook`` that raises a dropped :class:`Interrupted` again, else ``hook``.

    Python drops an exception raised where nothing can catch it (a weakref callback such
    as importlib's module-lock one, a ``__del__``) and reports it as "Exception ignored":
    a stop signal landing there would be lost with a traceback on stderr. It is not
    reported; it stays recorded (:func:`check` raises it) and the handler is called
    again from another thread a millisecond later (``_thread.interrupt_main``: no signal
    reaches the process), so that it raises in the code around; landing in such a place
    again, it is called again. A body of :func:`handle_signals` that ends first raises it
    on its way out. Unlike a signal, the call does not cut a blocking call short (a
    ``time.sleep``, a wait on a process): the stop waits for it to return.
    """
    def unraisable(info) -> None:
        if not (isinstance(info.exc_value, Interrupted) and _STATE.installed):
            hook(info)
            return
        if info.exc_value is not _STATE.raised:  # check()'s, in a finaliser: the signal
            return  # is recorded, and the next check raises it
        _STATE.dropped = info.exc_value.signum
        with contextlib.suppress(RuntimeError):  # no new thread at shutdown: see above
            _thread.start_new_thread(_raise_again, (_STATE.generation, _STATE.dropped))
        _STATE.raise_now = True  # it raised, so it could: it may again (set last, so that
        # a second signal does not raise in this hook)

    return unraisable


def _raise_again(generation: int, signum: int) -> None:
    """Calls the handler of ``signum`` in the main thread once the hook that asked returned.

    Not if it was raised since, or the handlers that dropped it are gone (``generation``:
    :attr:`_State.generation` when it was dropped).
    """
    time.sleep(0.001)
    if _STATE.installed and _STATE.generation == generation and _STATE.dropped == signum:
        _thread.interrupt_main(signum)


def stoppable() -> tuple[int, ...]:
    """The stop signals this process does not ignore, those its handlers take.

    One it ignores stays ignored: ``nohup hmpc sweep ... &`` keeps running when its
    terminal closes (SIGHUP), a background job ignores the terminal's Ctrl-C (SIGINT).
    """
    return tuple(s for s in STOP_SIGNALS if signal.getsignal(s) is not signal.SIG_IGN)


def install_deferred() -> None:
    """Installs the stop handlers for good, recording only (a sweep's worker process).

    The work stops at the next :func:`check`; only :func:`abortable` sections (IPOPT
    solves) are cut at once. Signals the process ignores stay ignored (:func:`stoppable`).
    """
    for s in stoppable():
        signal.signal(s, _handler)
    sys.unraisablehook = _unraisable(sys.unraisablehook)
    _STATE.installed, _STATE.raise_now = True, False


@contextlib.contextmanager
def handle_signals() -> Iterator[None]:
    """Installs the stop handlers for SIGINT, SIGTERM and SIGHUP; restores them on exit.

    Signals the process ignores stay ignored (:func:`stoppable`).

    Only in the main thread, and only the outermost (elsewhere, or nested: does nothing).
    The received signal is forgotten on entry. A stop whose raise Python dropped
    (:func:`_unraisable`) is raised on exit if the body ends first.
    """
    if threading.current_thread() is not threading.main_thread() or _STATE.installed:
        yield  # another thread's, or inside another handle_signals (or a worker's)
        return
    reset()
    previous = {s: signal.signal(s, _handler) for s in stoppable()}
    hook, sys.unraisablehook = sys.unraisablehook, _unraisable(sys.unraisablehook)
    _STATE.installed, _STATE.raise_now = True, True
    _STATE.generation += 1
    try:
        yield
        if _STATE.dropped is not None:  # the body ended before the stop was raised again
            raise Interrupted(_STATE.dropped)
    finally:
        _STATE.generation += 1  # a raise asked for now is stale
        _STATE.dropped = None
        for s, h in previous.items():
            signal.signal(s, h)
        sys.unraisablehook = hook
        _STATE.installed = False
