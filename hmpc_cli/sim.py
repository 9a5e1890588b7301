"""Fixed-step hybrid simulator: RK4 flow, exact guard location, resets.

One step integrates the flow of each sample's mode with RK4 over ``dt`` with the input
and disturbance held. If a guard of that mode is crossed inside the step (its gap goes
from > 0 to <= 0, and the crossing point lies in the guard's activity region), the first
crossing time tau is located by Illinois root finding on the RK4 sub-step
tau -> gap(RK4(x, tau)) to a bracket of ``time_tol`` seconds; the state past the guard is
reset, the mode switched, and the rest of the step integrated in the new mode. A guard
exactly at its level at the start of a sub-step does not fire (so a reset cannot re-trigger
its own guard). More than ``max_events`` events in one step is Zeno chattering: an error.

Everything is batched over samples (shape (B, n)) so the sampling planner's rollouts use
the very same code as the plant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hmpc_cli.hybrid import HybridSystem


class ZenoError(RuntimeError):
    """Raised when one step holds more guard events than allowed."""


@dataclass(frozen=True)
class Event:
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
    """Result of one batched step: states (B, n), modes (B,), events, Zeno flags (B,)."""

    x: np.ndarray
    mode: np.ndarray
    events: list[Event]
    zeno: np.ndarray


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
        self._source = np.array([system.mode_index(g.source) for g in system.guards])

    def rk4(self, mode: np.ndarray, x: np.ndarray, u: np.ndarray, w: np.ndarray,
            h: np.ndarray) -> np.ndarray:
        """One RK4 step of length h (B,) per sample in its mode; inputs saturated."""
        out = np.empty_like(x)
        modes = np.unique(mode)
        for m in modes:
            sel = slice(None) if len(modes) == 1 else mode == m
            out[sel] = self._rk4_mode(int(m), x[sel], u[sel], w[sel], h[sel])
        return out

    def _rk4_mode(self, m: int, x, u, w, h) -> np.ndarray:
        f = self.num.flows[m]
        u = np.clip(u, self.num.u_lower[m], self.num.u_upper[m])
        hc = h[:, None]
        k1 = f(x, u, w)[0]
        k2 = f(x + 0.5 * hc * k1, u, w)[0]
        k3 = f(x + 0.5 * hc * k2, u, w)[0]
        k4 = f(x + hc * k3, u, w)[0]
        return x + hc / 6.0 * (k1 + 2.0 * (k2 + k3) + k4)

    def step(self, x: np.ndarray, mode: np.ndarray, u: np.ndarray, w: np.ndarray,
             dt: float, record: bool = True, raise_zeno: bool = True) -> StepResult:
        """Advances every sample by ``dt`` seconds.

        Args:
            x: states (B, n). mode: mode indices (B,). u: inputs (B, m), held.
            w: disturbances (B, n_w), held. dt: step [s].
            record: collect :class:`Event` records (the planner switches this off).
            raise_zeno: raise :class:`ZenoError`; otherwise freeze and flag the sample.

        Returns:
            The new states and modes, the events in time order per sample, Zeno flags.
        """
        x = np.array(x, dtype=float)
        mode = np.array(mode, dtype=int)
        u = np.asarray(u, dtype=float)
        w = np.asarray(w, dtype=float)
        rem = np.full(x.shape[0], float(dt))
        n_events = np.zeros(x.shape[0], dtype=int)
        zeno = np.zeros(x.shape[0], dtype=bool)
        events: list[Event] = []
        todo = np.arange(x.shape[0])
        while todo.size:
            xa, ma, ua, wa, ha = x[todo], mode[todo], u[todo], w[todo], rem[todo]
            x_end = self.rk4(ma, xa, ua, wa, ha)
            tau, guard, x_hit = self._first_crossing(xa, ma, ua, wa, ha, x_end)
            hit = guard >= 0
            free = todo[~hit]
            x[free] = x_end[~hit]
            rem[free] = 0.0
            if not hit.any():
                break
            idx = todo[hit]
            for g in np.unique(guard[hit]):
                sel = guard[hit] == g
                rows = idx[sel]
                before = x_hit[hit][sel]
                after = self.num.reset(int(g), before)
                x[rows] = after
                mode[rows] = self.num.target[g]
                if record:
                    for j, r in enumerate(rows):
                        events.append(Event(int(r), float(dt - rem[r] + tau[hit][sel][j]),
                                            int(g), before[j].copy(), after[j].copy()))
            rem[idx] -= tau[hit]
            n_events[idx] += 1
            over = n_events > self.max_events
            if over.any():
                if raise_zeno:
                    raise ZenoError(f"more than {self.max_events} guard events in one step of "
                                    f"{dt} s (Zeno chattering) for sample(s) "
                                    f"{np.nonzero(over)[0].tolist()}")
                zeno |= over
                rem[over] = 0.0
            todo = idx[(rem[idx] > 0.0) & ~zeno[idx]]
        events.sort(key=lambda e: (e.sample, e.tau))
        return StepResult(x, mode, events, zeno)

    def _first_crossing(self, x, mode, u, w, h, x_end):
        """Earliest active guard crossing per sample: (tau (B,), guard (B,) or -1, state)."""
        b = x.shape[0]
        tau = h.copy()
        guard = np.full(b, -1)
        x_hit = x_end.copy()
        for g in range(len(self.system.guards)):
            cand = np.nonzero(mode == self._source[g])[0]
            if cand.size == 0:
                continue
            g0 = self.num.gap(g, x[cand])
            g1 = self.num.gap(g, x_end[cand])
            cross = (g0 > 0.0) & (g1 <= 0.0)
            if not cross.any():
                continue
            rows = cand[cross]
            t_g, x_g = self._locate(g, x[rows], mode[rows], u[rows], w[rows], h[rows],
                                    g0[cross], g1[cross], x_end[rows])
            ok = self.num.active(g, x_g) & ((t_g < tau[rows]) | (guard[rows] < 0))
            rows, t_g, x_g = rows[ok], t_g[ok], x_g[ok]
            tau[rows] = t_g
            guard[rows] = g
            x_hit[rows] = x_g
        return tau, guard, x_hit

    def _locate(self, g, x, mode, u, w, h, f_lo, f_hi, x_hi):
        """Root of gap(RK4(x, tau)) on (0, h], bracketed to ``time_tol``.

        Each iteration takes the regula-falsi estimate and evaluates a pair of points
        straddling it (one batched call), half as far apart as the last two estimates,
        so both ends of the bracket close in a few iterations. Returns the past side.
        """
        lo = np.zeros_like(h)
        hi = h.copy()
        f_lo, f_hi, x_hi = f_lo.copy(), f_hi.copy(), x_hi.copy()
        t_prev = h.copy()
        tol = self.time_tol
        xx, mm, uu, ww = (np.concatenate([a, a]) for a in (x, mode, u, w))
        for _ in range(100):
            done = (hi - lo <= tol) | (f_hi == 0.0)
            if done.all():
                break
            width = hi - lo
            t_est = hi - f_hi * width / (f_hi - f_lo)
            t_est = np.where(np.isfinite(t_est), t_est, lo + 0.5 * width)
            delta = np.clip(0.5 * np.abs(t_est - t_prev), 0.4 * tol, 0.25 * width)
            t_prev = t_est
            t_a = np.clip(t_est - delta, lo + 0.1 * tol, hi)
            t_b = np.clip(t_est + delta, lo, hi - 0.1 * tol)
            x_t = self.rk4(mm, xx, uu, ww, np.concatenate([t_a, t_b]))
            f_t = self.num.gap(g, x_t)
            n = len(h)
            for t, f, xs in ((t_a, f_t[:n], x_t[:n]), (t_b, f_t[n:], x_t[n:])):
                past = (f <= 0.0) & (t < hi) & ~done
                before = (f > 0.0) & (t > lo) & ~done
                hi = np.where(past, t, hi)
                f_hi = np.where(past, f, f_hi)
                x_hi[past] = xs[past]
                lo = np.where(before, t, lo)
                f_lo = np.where(before, f, f_lo)
        return hi, x_hi
