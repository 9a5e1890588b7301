"""Disturbance processes w(t), held piecewise constant on a knot grid.

``box``: a seeded uniform process in [-magnitude, magnitude]^n_w, a new value every
``hold`` seconds (NumPy PCG64 seeded with the run seed). ``paper_fig3``: the exact recipe of
the paper's Figure 3 (MT19937 seeded 5489; for trial i = 1..10 in order, 61 uniforms for
w_x then 61 for w_y on the knots t = 0, 0.05, ..., 3.0; w = 2 * magnitude * (U - 0.5)).
``none``: w = 0. Past the last knot the last value is held.
"""

from __future__ import annotations

import numpy as np

PAPER_SEED = 5489
PAPER_KNOTS = 61
PAPER_HOLD = 0.05


class HeldDisturbance:
    """w(t) = values[k] for t in [k * hold, (k + 1) * hold); shape (K, n_w)."""

    def __init__(self, values: np.ndarray, hold: float) -> None:
        self.values = np.asarray(values, dtype=float)
        self.hold = float(hold)

    @property
    def n_w(self) -> int:
        """Number of disturbance channels."""
        return self.values.shape[1]

    def knot(self, t: float) -> int:
        """Index of the knot in force at time t [s] (robust to round-off at knots)."""
        k = int(np.floor(t / self.hold + 1e-9))
        return min(max(k, 0), len(self.values) - 1)

    def __call__(self, t: float) -> np.ndarray:
        """w(t), shape (n_w,)."""
        return self.values[self.knot(t)]


def paper_fig3_sequence(trial: int, magnitude: float = 10.0, n_w: int = 2) -> np.ndarray:
    """Knot values (61, n_w) of trial ``trial`` (1..10) of the paper's Figure 3 recipe."""
    if not 1 <= trial <= 10:
        raise ValueError(f"paper_fig3 trial must be in 1..10, got {trial}")
    stream = np.random.RandomState(PAPER_SEED).random_sample(10 * n_w * PAPER_KNOTS)
    block = stream[(trial - 1) * n_w * PAPER_KNOTS: trial * n_w * PAPER_KNOTS]
    uniforms = block.reshape(n_w, PAPER_KNOTS).T
    return 2.0 * magnitude * (uniforms - 0.5)


#: the disturbance keys each kind reads (beside ``kind``)
READS = {"none": (), "box": ("magnitude", "hold"), "paper_fig3": ("magnitude", "trial")}


def inert_keys(kind: str, given) -> list[str]:
    """``disturbance.<key>: no effect ...`` for each key in ``given`` that ``kind`` ignores."""
    why = {"hold": f"(the paper's sequence holds each value {PAPER_HOLD:g} s)"
           if kind == "paper_fig3" else "", "trial": "(trial picks a paper_fig3 sequence)"}
    return [f"disturbance.{key}: no effect with disturbance.kind = {kind!r}"
            + (f" {why[key]}" if why.get(key) else "")
            for key in sorted(set(given) - {"kind"}) if key not in READS.get(kind, ())]


def knot_period(kind: str, hold: float) -> float | None:
    """The time [s] each value of ``kind``'s process is held (None: ``none``, one value)."""
    return {"box": hold, "paper_fig3": PAPER_HOLD}.get(kind)


def make_disturbance(kind: str, *, n_w: int, duration: float, magnitude: float = 0.0,
                     hold: float = PAPER_HOLD, seed: int = 0, trial: int = 1) -> HeldDisturbance:
    """Builds the disturbance process of a scenario.

    Args:
        kind: ``none``, ``box`` or ``paper_fig3``.
        n_w: number of disturbance channels.
        duration: run length [s] (the box process draws knots to cover it).
        magnitude: half-width of the uniform box per channel.
        hold: hold period [s] (``box`` only; the paper recipe uses 0.05 s).
        seed: seed of the ``box`` process.
        trial: trial 1..10 of the paper recipe.
    """
    if kind == "none":
        return HeldDisturbance(np.zeros((1, n_w)), hold)
    if kind == "paper_fig3":
        return HeldDisturbance(paper_fig3_sequence(trial, magnitude, n_w), PAPER_HOLD)
    if kind == "box":
        knots = int(np.floor(duration / hold + 1e-9)) + 1
        rng = np.random.Generator(np.random.PCG64(seed))
        return HeldDisturbance(rng.uniform(-magnitude, magnitude, size=(knots, n_w)), hold)
    raise ValueError(f"unknown disturbance kind {kind!r}")
