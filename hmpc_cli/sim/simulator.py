"""Fixed-step hybrid simulator: RK4 flow, exact guard location, resets.

One step integrates the flow of each sample's mode with RK4 over ``dt`` with the input
and disturbance held. If a guard of that mode is crossed inside the step (its gap goes
from > 0 to <= 0, and the crossing point lies in the guard's activity region), the first
crossing time tau is located by root finding on the RK4 sub-step
tau -> gap(RK4(x, tau)) to a bracket of ``time_tol`` seconds; the state at the bracket's
near side is reset, the mode switched, and the rest of the step integrated in the new mode. A guard
exactly at its level at the start of a sub-step does not fire (so a reset cannot re-trigger
its own guard). More than ``max_events`` events in one step is Zeno chattering: an error.

Everything is batched over samples (shape (B, n)) so the sampling planner's rollouts use
the very same code as the plant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hmpc_cli.core.hybrid import HybridSystem


def zeno_text(max_events: int, h: float) -> str:
    """The reason of a step of ``h`` seconds with more than ``max_events`` events."""
    return (f"more than {max_events} guard event{'s' if max_events != 1 else ''} in one "
            f"step of {h:.6g} s (Zeno chattering)")


class ZenoError(RuntimeError):
    """Raised when one step holds more guard events than allowed."""


@dataclass(frozen=True)
class StepEvent:
    """A guard event of sample ``sample`` at ``tau`` seconds into the step.

    Attributes:
        sample: batch index.
        tau: time from the start of the step [s].
        guard: guard index.
        x_before: state on the guard before the reset, shape (n,).
        x_after: state after the reset, shape (n,).
    """

    sample: int
    tau: float
    guard: int
    x_before: np.ndarray
    x_after: np.ndarray


@dataclass(frozen=True)
class StepResult:
    """Result of one batched step.

    Attributes:
        x: states (B, n) at the end of the step.
        mode: modes (B,) at the end of the step.
        events: guard events, in time order per sample (empty unless recorded).
        zeno: Zeno flags (B,): samples frozen after too many events.
        remaining: time not integrated (B,) [s] (nonzero only with ``stop_at_event``).
    """

    x: np.ndarray
    mode: np.ndarray
    events: list[StepEvent]
    zeno: np.ndarray
    remaining: np.ndarray | None = None


class HybridSimulator:
    """Steps a hybrid system with RK4 and exact event location.

    Args:
        system: the hybrid system.
        max_events: events allowed in one step before declaring Zeno chattering.
        time_tol: width of the final bracket around each event time [s].
    """

    def __init__(self, system: HybridSystem, max_events: int = 10, time_tol: float = 1e-10):
        self.system = system
        self.num = system.numeric
        self.max_events = max_events
        self.time_tol = time_tol

    def rk4(self, mode: np.ndarray, x: np.ndarray, u: np.ndarray, w: np.ndarray,
            h: np.ndarray) -> np.ndarray:
        """One RK4 step of length h (B,) per sample in its mode; inputs saturated."""
        m0 = int(mode[0])
        if (mode == m0).all():
            return self.num.rk4[m0](x, u, w, h[:, None])[0]
        out = np.empty_like(x)
        for m in np.unique(mode):
            sel = mode == m
            out[sel] = self.num.rk4[int(m)](x[sel], u[sel], w[sel], h[sel, None])[0]
        return out

    def step(self, x: np.ndarray, mode: np.ndarray, u: np.ndarray, w: np.ndarray,
             dt: float, record: bool = True, raise_zeno: bool = True,
             stop_at_event: bool = False) -> StepResult:
        """Advances every sample by ``dt`` seconds.

        Args:
            x: states (B, n).
            mode: mode indices (B,).
            u: inputs (B, m), held over the step.
            w: disturbances (B, n_w), held over the step.
            dt: step [s].
            record: collect :class:`StepEvent` records (the planner switches this off).
            raise_zeno: raise :class:`ZenoError`; otherwise freeze and flag the sample.
            stop_at_event: a sample stops right after its first reset (post-reset state)
                and reports the time left in ``remaining``, so the caller can compute a
                new input for the rest of the step (needed when a reset relabels the
                inputs, as the biped's leg swap does).

        Returns:
            The new states and modes, the events in time order per sample, Zeno flags,
            the time left per sample.

        Raises:
            ZenoError: more than ``max_events`` events in the step (with ``raise_zeno``).
        """
        x = np.asarray(x, dtype=float)
        mode = np.array(mode, dtype=int)
        u = np.asarray(u, dtype=float)
        w = np.asarray(w, dtype=float)
        b = x.shape[0]
        rem = np.full(b, float(dt))
        # first pass over the whole batch without copies; most steps end here
        x_end = self.rk4(mode, x, u, w, rem)
        crossing = self._first_crossing(x, mode, u, w, rem, x_end)
        if crossing is None or (crossing[1] < 0).all():
            return StepResult(x_end, mode, [], np.zeros(b, dtype=bool), np.zeros(b))
        return self._step_through_events(
            x.copy(), mode, u, w, dt, rem, (x_end, *crossing),
            record=record, raise_zeno=raise_zeno, stop_at_event=stop_at_event)

    def _step_through_events(self, x, mode, u, w, dt, rem, first_pass, *, record,
                             raise_zeno, stop_at_event) -> StepResult:
        """The rest of :meth:`step` once a sample crosses a guard: one event per pass.

        ``x`` (the caller's copy), ``mode`` and ``rem`` (time left [s], (B,)) are updated
        in place. ``first_pass`` is (x_end, tau, guard, x_hit) of the whole batch over the
        full step; each later pass integrates the samples still running over their time
        left. The other arguments are those of :meth:`step`.
        """
        x_end, tau, guard, x_hit = first_pass
        b = x.shape[0]
        zeno = np.zeros(b, dtype=bool)
        n_events = np.zeros(b, dtype=int)
        events: list[StepEvent] = []
        todo = np.arange(b)
        while True:
            hit = guard >= 0
            free = todo[~hit]
            x[free] = x_end[~hit]
            rem[free] = 0.0
            if not hit.any():
                break
            idx = todo[hit]
            self._reset(x, mode, idx, guard[hit], x_hit[hit],
                        dt - rem[idx] + tau[hit] if record else None, events)
            rem[idx] -= tau[hit]
            self._count_events(idx, n_events, zeno, rem, dt, raise_zeno)
            if stop_at_event:
                break
            todo = idx[(rem[idx] > 0.0) & ~zeno[idx]]
            if not todo.size:
                break
            xa, ma, ua, wa, ha = x[todo], mode[todo], u[todo], w[todo], rem[todo]
            x_end = self.rk4(ma, xa, ua, wa, ha)
            tau, guard, x_hit = self._first_crossing(xa, ma, ua, wa, ha, x_end) or (
                ha, np.full(len(todo), -1), x_end)
        events.sort(key=lambda e: (e.sample, e.tau))
        return StepResult(x, mode, events, zeno, rem)

    def _reset(self, x, mode, idx, guard, x_hit, t_event, events: list[StepEvent]) -> None:
        """Applies the reset maps in place: sample idx[i] hit guard[i] in state x_hit[i].

        Args:
            x: states (B, n), rows ``idx`` overwritten with the post-reset states.
            mode: modes (B,), rows ``idx`` set to the guards' target modes.
            idx: batch indices (k,) of the samples that hit a guard.
            guard: guard index per hit (k,).
            x_hit: states on the guards before the reset (k, n).
            t_event: event times from the start of the step (k,) [s], or None to record
                no :class:`StepEvent`.
            events: the events so far; one is appended per hit unless ``t_event`` is None.
        """
        for g in np.unique(guard):
            sel = guard == g
            rows = idx[sel]
            before = x_hit[sel]
            after = self.num.reset(int(g), before)
            x[rows] = after
            mode[rows] = self.num.target[g]
            if t_event is not None:
                for j, r in enumerate(rows):
                    events.append(StepEvent(int(r), float(t_event[sel][j]), int(g),
                                        before[j].copy(), after[j].copy()))

    def _count_events(self, idx, n_events, zeno, rem, dt, raise_zeno) -> None:
        """Counts one more event for samples ``idx``; handles those over ``max_events``.

        ``n_events`` (B,) is incremented in place. A sample over the limit raises
        :class:`ZenoError` if ``raise_zeno``, else it is flagged in ``zeno`` (B,) and
        frozen (its time left ``rem`` set to 0).
        """
        n_events[idx] += 1
        over = n_events > self.max_events
        if over.any():
            if raise_zeno:
                which = (f" for sample(s) {np.nonzero(over)[0].tolist()}"
                         if len(over) > 1 else "")
                raise ZenoError(zeno_text(self.max_events, dt) + which)
            zeno |= over
            rem[over] = 0.0

    def _first_crossing(self, x, mode, u, w, h, x_end):
        """Earliest active guard crossing per sample: (tau (B,), guard (B,) or -1, state).

        All guards of a mode are located together: for each sample, the root of the
        smallest gap among the guards it crosses in this step. A crossing outside the
        guard's activity region is dropped and the sample searched again without it.
        None when no sample's gaps cross (most steps).
        """
        b = x.shape[0]
        found = None  # (tau, guard, x_hit), made at the first crossing
        single = bool((mode == mode[0]).all())
        for m in ((int(mode[0]),) if single else np.unique(mode)):
            guards = self.num.guards_of[m]
            if not guards:
                continue
            if single:
                cand, g0 = None, self.num.mode_gaps[m](x)[0]
                g1 = self.num.mode_gaps[m](x_end)[0]
            else:
                cand = np.nonzero(mode == m)[0]
                g0 = self.num.mode_gaps[m](x[cand])[0]
                g1 = self.num.mode_gaps[m](x_end[cand])[0]
            cross = (g0 > 0.0) & (g1 <= 0.0)
            if not cross.any():  # most steps: no guard of this mode crossed
                continue
            if cand is None:
                cand = np.arange(b)
            if found is None:
                found = h.copy(), np.full(b, -1), x_end.copy()
            tau, guard, x_hit = found
            while True:
                rows = np.nonzero(cross.any(axis=1))[0]
                if rows.size == 0:
                    break
                idx = cand[rows]
                t_g, c_g, x_g = self._locate(m, x[idx], u[idx], w[idx], h[idx],
                                             cross[rows], g0[rows], g1[rows])
                g_idx = np.asarray(guards)[c_g]
                active = np.ones(len(idx), dtype=bool)
                for g in np.unique(g_idx):
                    sel = g_idx == g
                    active[sel] = self.num.active(int(g), x_g[sel])
                tau[idx[active]] = t_g[active]
                guard[idx[active]] = g_idx[active]
                x_hit[idx[active]] = x_g[active]
                cross[rows[active]] = False
                cross[rows[~active], c_g[~active]] = False
        return found

    def _locate(self, m, x, u, w, h, cross, f0, f1):
        """First root of phi(tau) = min over crossing guards of gap(RK4(x, tau)) on (0, h].

        Safeguarded Newton on the exact RK4 sub-step (dphi/dtau by CasADi AD), biased by
        a fraction of the tolerance so that, once converged, consecutive iterates land on
        both sides of the root and close the bracket to ``time_tol``. Returns the
        bracket's *before* side (time, guard column, state with every gap > 0), so the
        reset state never starts past a guard and an immediate re-crossing is seen.
        """
        tol = self.time_tol
        phi_fn = self.num.gaps_along[m]
        rows = np.arange(len(h))
        lo = np.zeros_like(h)
        hi = h.copy()
        x_lo = x.copy()
        col = np.argmin(np.where(cross, 0.0, 1.0), axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(cross, h[:, None] * f0 / (f0 - f1), np.inf).min(axis=1)
        t = np.where(np.isfinite(t) & (t > 0.0) & (t < h), t, 0.5 * h)
        one = bool((cross.sum(axis=1) == 1).all())  # common case: one guard per sample
        for _ in range(60):
            phis, dphis, x_t = phi_fn(x, u, w, t[:, None])
            c = col if one else np.argmin(np.where(cross, phis, np.inf), axis=1)
            phi, dphi = phis[rows, c], dphis[rows, c]
            past = phi <= 0.0
            hi = np.where(past, np.minimum(t, hi), hi)
            lo = np.where(past, lo, np.maximum(t, lo))
            if not one:
                col = np.where(past, c, col)
            x_lo[~past] = x_t[~past]
            if ((hi - lo) <= tol).all():
                break
            t_new = t - np.divide(phi, dphi, out=np.full_like(phi, np.nan), where=dphi != 0.0)
            t_new += np.where(past, -0.4 * tol, 0.4 * tol)
            bad = ~((t_new > lo) & (t_new < hi))
            t = np.where(bad, 0.5 * (lo + hi), t_new)
        return lo, col, x_lo
