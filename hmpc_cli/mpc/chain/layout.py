"""Node schedules of the fixed-mode MPC: node counts per domain and node shifting.

The horizon has ``N`` flow intervals of ``dt`` seconds, split over the scheduled domains
D_0..D_S (``counts[j]`` intervals in D_j, summing to N). The NLP is one chain of
``L = N + S_max`` links: the intervals of D_0, then a reset link at D_0's guard node (whose
input is the *virtual* input that drives the virtual pass-through node past the guard),
the intervals of D_1, ..., the intervals of D_S, and identity "hold" links that pad the
chain to its fixed length. The chain's length never changes, so the NLP is built once.

Node shifting (the paper, Sec. III): each MPC period moves exactly the elapsed intervals
from the current domain to the final domain; a domain whose planned guard time has passed
without an impact keeps one interval (its guard stays planned one node ahead). On a real
impact the remaining intervals of that domain, virtual node included, move to the final
domain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hmpc_cli.core.messages import ModeSchedule

FLOW, RESET, HOLD = 0, 1, 2


@dataclass(frozen=True)
class NodeSchedule:
    """Domains, guards and interval counts of one MPC problem.

    Attributes:
        modes: domain sequence (mode indices), final domain last.
        guards: guard sequence (len(modes) - 1 guard indices).
        counts: flow intervals per domain (len(modes) integers >= 1, sum N).
    """

    modes: tuple[int, ...]
    guards: tuple[int, ...]
    counts: tuple[int, ...]

    def __post_init__(self) -> None:
        if len(self.modes) != len(self.guards) + 1 or len(self.counts) != len(self.modes):
            raise ValueError("NodeSchedule: need S guards and S + 1 modes and counts")
        if min(self.counts) < 1:
            raise ValueError(f"NodeSchedule: every domain needs >= 1 interval: {self.counts}")

    @property
    def n_intervals(self) -> int:
        """N, the flow intervals over the horizon."""
        return sum(self.counts)

    @classmethod
    def from_schedule(cls, schedule: ModeSchedule, n: int, dt: float) -> NodeSchedule:
        """The node schedule of a mode schedule on ``n`` intervals of ``dt`` seconds.

        Planned durations are rounded up to whole intervals (so a plan that needed all
        of its time stays feasible); the final domain takes the rest.

        Raises:
            ValueError: the non-final domains do not fit in ``n - 1`` intervals.
        """
        counts = [max(1, int(np.ceil(d / dt - 1e-6))) for d in schedule.durations]
        final = n - sum(counts)
        if final < 1:
            raise ValueError(f"schedule of {sum(schedule.durations):.3f} s before the final "
                             f"domain, {sum(counts)} node intervals of {dt:.4g} s once each "
                             f"domain is rounded up to whole intervals, leaves the final "
                             f"domain none of the MPC horizon's {n} ({n * dt:.3f} s)")
        return cls(schedule.modes, schedule.guards, tuple(counts) + (final,))

    def shift(self, elapsed: int) -> tuple[NodeSchedule, int]:
        """Moves ``elapsed`` intervals from the current to the final domain.

        Returns:
            The new schedule and the number of intervals actually moved (the current
            domain keeps at least one interval while its guard is pending).
        """
        if len(self.counts) == 1:
            return self, 0
        moved = min(elapsed, self.counts[0] - 1)
        counts = (self.counts[0] - moved,) + self.counts[1:-1] + (self.counts[-1] + moved,)
        return NodeSchedule(self.modes, self.guards, counts), moved

    def on_impact(self) -> NodeSchedule:
        """Drops the current domain after a real impact with its guard."""
        if len(self.counts) == 1:
            raise ValueError("no pending guard: already in the final domain")
        counts = self.counts[1:-1] + (self.counts[-1] + self.counts[0],)
        return NodeSchedule(self.modes[1:], self.guards[1:], counts)

    def to_dict(self) -> dict:
        """JSON-ready dict of modes, guards and counts."""
        return {"modes": list(self.modes), "guards": list(self.guards),
                "counts": list(self.counts)}


@dataclass(frozen=True)
class ChainLayout:
    """Per-link and per-node roles of a node schedule on a chain of ``length`` links.

    Attributes:
        link_type: FLOW, RESET or HOLD per link, shape (L,).
        link_mode: mode of flow links (and source mode of reset links), else -1.
        link_guard: guard of reset links, else -1.
        seg: domain segment of each node, shape (L + 1,) (-1 for hold nodes).
        local: index of each node inside its segment (0 = first node).
        first_after_reset: node is the first node of a domain entered by a reset.
        last: index of the last real node (before the hold padding).
    """

    link_type: np.ndarray
    link_mode: np.ndarray
    link_guard: np.ndarray
    seg: np.ndarray
    local: np.ndarray
    first_after_reset: np.ndarray
    last: int

    @classmethod
    def build(cls, ns: NodeSchedule, length: int) -> ChainLayout:
        """Lays a node schedule out on a chain of ``length`` links."""
        used = ns.n_intervals + len(ns.guards)
        if used > length:
            raise ValueError(f"schedule needs {used} links, the NLP chain has {length}: "
                             "raise mpc.max_switches")
        link_type = np.full(length, HOLD)
        link_mode = np.full(length, -1)
        link_guard = np.full(length, -1)
        seg = np.full(length + 1, -1)
        local = np.zeros(length + 1, dtype=int)
        first = np.zeros(length + 1, dtype=bool)
        k = 0
        for j, (mode, count) in enumerate(zip(ns.modes, ns.counts, strict=True)):
            first[k] = j > 0
            for i in range(count + 1):
                seg[k + i], local[k + i] = j, i
            link_type[k:k + count] = FLOW
            link_mode[k:k + count] = mode
            k += count
            if j < len(ns.guards):
                link_type[k], link_mode[k], link_guard[k] = RESET, mode, ns.guards[j]
                k += 1
        return cls(link_type, link_mode, link_guard, seg, local, first, k)

    def node_of(self, seg: int, local: int) -> int:
        """Chain index of node ``local`` of segment ``seg`` (local clamped to the segment)."""
        idx = np.nonzero(self.seg == seg)[0]
        return int(idx[min(max(local, 0), len(idx) - 1)])


def remap(old: ChainLayout, new: ChainLayout, dropped: int, offset0: int) -> np.ndarray:
    """For every node of ``new``, the node of ``old`` holding the same planned point.

    Args:
        old: layout the values are stored in.
        new: layout to fill.
        dropped: segments removed at the front (1 after an impact, else 0).
        offset0: intervals elapsed in the current segment (0 after an impact).

    Returns:
        Old node index per new node, shape (L + 1,); hold nodes map to old.last.
    """
    out = np.full(new.seg.shape, old.last)
    k = np.arange(new.last + 1)
    j = new.seg[k]
    local = new.local[k] + np.where(j == 0, offset0, 0)
    # segments are contiguous runs of nodes: their first node and length in old
    n_seg = int(old.seg.max()) + 1
    first = np.searchsorted(old.seg[: old.last + 1], np.arange(n_seg))
    length = np.bincount(old.seg[old.seg >= 0], minlength=n_seg)
    src = j + dropped
    out[k] = first[src] + np.clip(local, 0, length[src] - 1)
    return out
