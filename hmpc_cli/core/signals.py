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
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator

__all__ = ["EXIT_CODES", "Interrupted", "abortable", "as_interrupted", "check", "deferred",
           "handle_signals", "install_deferred", "pending", "reset"]

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


_STATE = _State()


def _handler(signum: int, frame) -> None:
    if _STATE.signum is None:
        _STATE.signum = int(signum)
    if _STATE.raise_now:
        _STATE.raise_now = False  # raise once; the code then checks the flag
        raise Interrupted(_STATE.signum)


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
    _STATE.signum = None


def check() -> None:
    """Raises :class:`Interrupted` if a stop signal was received.

    Raises:
        Interrupted: a stop signal is pending.
    """
    if _STATE.signum is not None:
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
    """``sys.stderr`` inside :func:`abortable`, without CasADi's interrupt warning.

    Forwards everything but CasADi's warning about the interrupt it caught in an IPOPT
    callback (the command reports the stop in its own one line). Once a stop signal is
    pending, text is forwarded a whole line at a time (CasADi writes its warning in
    pieces).
    """

    def __init__(self, stream) -> None:
        self._stream = stream
        self._line = ""

    def write(self, text: str) -> int:
        if _STATE.signum is None and not self._line:
            return self._stream.write(text)
        self._line += text
        while "\n" in self._line:
            line, self._line = self._line.split("\n", 1)
            self._forward(line + "\n")
        return len(text)

    def _forward(self, text: str) -> None:
        if CASADI_INTERRUPT not in text:
            self._stream.write(text)

    def close_section(self) -> None:
        """Forwards a partial line left at the section's end (unless CasADi's warning)."""
        line, self._line = self._line, ""
        if line:
            self._forward(line)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


#: the text of CasADi's warning when a callback of IPOPT raised KeyboardInterrupt
CASADI_INTERRUPT = 'WARNING("KeyboardInterruptException")'


@contextlib.contextmanager
def abortable() -> Iterator[None]:
    """A long computation a signal may cut (an IPOPT solve); checks on entry and exit.

    Raises:
        Interrupted: a stop signal is pending, or arrives during the section.
    """
    check()
    stream = sys.stderr
    sys.stderr = quiet = _Unreported(stream)
    try:
        with _raising(True):
            yield
    finally:
        sys.stderr = stream
        quiet.close_section()
    check()


def install_deferred() -> None:
    """Installs the stop handlers for good, recording only (a sweep's worker process).

    The work stops at the next :func:`check`; only :func:`abortable` sections (IPOPT
    solves) are cut at once.
    """
    for s in STOP_SIGNALS:
        signal.signal(s, _handler)
    _STATE.installed, _STATE.raise_now = True, False


@contextlib.contextmanager
def handle_signals() -> Iterator[None]:
    """Installs the stop handlers for SIGINT, SIGTERM and SIGHUP; restores them on exit.

    Only in the main thread (elsewhere: does nothing). The received signal is forgotten on
    entry.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    reset()
    previous = {s: signal.signal(s, _handler) for s in STOP_SIGNALS}
    _STATE.installed, _STATE.raise_now = True, True
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _STATE.installed = False
