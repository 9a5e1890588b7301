"""An ``nlpsol`` called on NumPy buffers (CasADi's ``Function.buffer``).

A plain call of a CasADi Function converts every input array to a ``DM`` and every
output back, on every call; for the MPC's NLPs (8 inputs, 6 outputs of ~10^3 entries)
that costs about as much as a real-time iteration's function evaluations. A
:class:`BufferedSolver` binds one array per input and output once and evaluates the
solver on them: the same solver, the same memory layout, bit-identical results.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

__all__ = ["BufferedSolver"]

#: stats entries CasADi accumulates over a buffer's calls (differenced per call)
_CUMULATIVE = ("n_call_", "t_wall_", "t_proc_")


class BufferedSolver:
    """A solver Function (``ca.nlpsol``) evaluated through a ``FunctionBuffer``.

    Called with the solver's keyword inputs (``x0``, ``p``, ``lbx``, ...; one missing
    takes the solver's default, as in a plain call), it returns a dict of its outputs as
    1-D arrays (copies). :meth:`stats` is the last call's: CasADi's call counters and
    timers of that call alone. Any other attribute is the wrapped Function's
    (``get_function``, ``has_function``, ``name``, ...).

    Args:
        function: the solver Function.
    """

    def __init__(self, function: ca.Function) -> None:
        """Binds an input and an output array per slot of ``function``."""
        self.function = function
        self._buffer, self._evaluate = function.buffer()
        self._index = {name: i for i, name in enumerate(function.name_in())}
        self._defaults = [np.full(function.nnz_in(i), float(function.default_in(i)))
                          for i in range(function.n_in())]
        self._in = [d.copy() for d in self._defaults]
        self._out = {name: np.zeros(function.nnz_out(i))
                     for i, name in enumerate(function.name_out())}
        for i, arr in enumerate(self._in):
            self._buffer.set_arg(i, memoryview(arr))
        for i, arr in enumerate(self._out.values()):
            self._buffer.set_res(i, memoryview(arr))
        self._total: dict = {}
        self._last: dict = {}
        self._objective: tuple | None = None  # nlp_f's buffer (:meth:`objective`)

    def __call__(self, **inputs) -> dict[str, np.ndarray]:
        """One solve; see the class docstring.

        Raises:
            ValueError: an unknown input name, or an input of the wrong size.
            BaseException: an exception raised inside the solve (a signal handler's
                ``KeyboardInterrupt``), as it was raised.
            RuntimeError: CasADi's, as a plain call raises it.
        """
        given = set(inputs)
        for name, value in inputs.items():
            i = self._index.get(name)
            if i is None:
                raise ValueError(f"{self.function.name()}: no input {name!r} "
                                 f"(inputs: {', '.join(self._index)})")
            flat = np.ravel(np.asarray(value, dtype=float))
            if flat.size == 1 and self._in[i].size != 1:  # a scalar fills the input
                self._in[i].fill(flat[0])
            elif flat.size != self._in[i].size:
                raise ValueError(f"{self.function.name()}: input {name!r} has "
                                 f"{flat.size} entries, expected {self._in[i].size}")
            else:
                np.copyto(self._in[i], flat)
        for name, i in self._index.items():
            if name not in given:
                np.copyto(self._in[i], self._defaults[i])
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            self._evaluate()
        except SystemError as exc:  # a Python exception inside the solver's callbacks
            if exc.__cause__ is not None:
                raise exc.__cause__ from None
            raise
        self._record(time.perf_counter() - wall, time.process_time() - cpu)
        return {name: arr.copy() for name, arr in self._out.items()}

    def _record(self, wall: float, cpu: float) -> None:
        """Keeps the last call's stats: CasADi's running counters and timers differenced.

        The call's own timer (``total``, which a buffer skips) is ``wall`` and ``cpu`` [s].
        """
        total = self._buffer.stats()
        last = dict(total)
        for key, value in total.items():
            if key.startswith(_CUMULATIVE) and isinstance(value, (int, float)):
                last[key] = value - self._total.get(key, 0)
        if "t_wall_total" in last:  # record_time
            last.update(t_wall_total=wall, t_proc_total=cpu, n_call_total=1)
        self._total, self._last = total, last

    def stats(self) -> dict:
        """The last call's stats (see the class docstring)."""
        return dict(self._last)

    def objective(self, w: np.ndarray, p: np.ndarray) -> float:
        """The solver's ``nlp_f`` at primal point w (nx,) and parameters p (np,), buffered.

        The same function as ``get_function("nlp_f")(w, p)``, without converting its
        arguments to ``DM`` on every call.

        Raises:
            RuntimeError: the solver has no ``nlp_f`` (``has_function``).
        """
        if self._objective is None:
            f = self.function.get_function("nlp_f")
            buffer, evaluate = f.buffer()
            args = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
            out = np.zeros(f.nnz_out(0))
            for i, arr in enumerate(args):
                buffer.set_arg(i, memoryview(arr))
            buffer.set_res(0, memoryview(out))
            self._objective = (buffer, evaluate, args, out)
        _, evaluate, args, out = self._objective
        np.copyto(args[0], np.ravel(w))
        np.copyto(args[1], np.ravel(p))
        evaluate()
        return float(out[0])

    def __getattr__(self, name: str):
        """The wrapped Function's attribute ``name``."""
        return getattr(self.function, name)
