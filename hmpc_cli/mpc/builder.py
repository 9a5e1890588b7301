"""A small structured-NLP builder: named blocks of variables, parameters and rows.

Variables, parameters and constraint rows are registered as named *blocks* of a given
shape; the flat vectors ``x``, ``p`` and ``g`` hold the blocks' entries in registration
order. A block registered inside :meth:`NLPBuilder.stage` is *staged*: registered once
per stage, so different blocks interleave stage by stage (the banded KKT structure IPOPT
likes, the stage-wise order fatrop needs); its index array stacks the stages, shape
``(stages, *shape)``. An unstaged block is registered once; its index array has its
shape. Matrix blocks are flattened column-major (as ``casadi.vec``).

Example::

    b, z = NLPBuilder(), []
    a = b.parameter("a", (L, M))              # layout.p["a"]: shape (L, M)
    for k in range(L + 1):
        with b.stage(k):
            z.append(b.variable("z", n))      # layout.x["z"]: shape (L + 1, n)
    for k in range(L):
        with b.stage(k):
            b.rows("dynamics", z[k + 1] - f(z[k], a[k, :]))   # layout.g["dynamics"]: (L, n)
    nlp, layout = b.build(cost)
    bounds = layout.bounds()                  # -inf / +inf, filled by name:
    bounds.lbx["z"][0] = bounds.ubx["z"][0] = x0
    lbx, ubx, lbg, ubg = bounds.arrays()
    p = layout.p.pack({"a": a_values})
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass

import casadi as ca
import numpy as np

Shape = int | tuple[int, ...]


def _shape(shape: Shape) -> tuple[int, ...]:
    return (shape,) if isinstance(shape, int | np.integer) else tuple(int(d) for d in shape)


@dataclass(frozen=True)
class _Entry:
    """One registration of a block: its stage (None: unstaged), offset and shape."""

    stage: Hashable | None
    offset: int
    shape: tuple[int, ...]

    def indices(self) -> np.ndarray:
        size = math.prod(self.shape)
        return np.arange(self.offset, self.offset + size).reshape(self.shape, order="F")


class _View:
    """Writable view of one block of a flat vector: ``view[key]`` indexes the block."""

    def __init__(self, flat: np.ndarray, idx: np.ndarray) -> None:
        self._flat, self._idx = flat, idx

    def __getitem__(self, key) -> np.ndarray:
        return self._flat[self._idx[key]]

    def __setitem__(self, key, value) -> None:
        self._flat[self._idx[key]] = value


class NamedVector:
    """A flat vector ``flat`` addressed by block name: ``v["guard_avoid"][k, c] = 0.0``."""

    def __init__(self, flat: np.ndarray, blocks: Blocks) -> None:
        """Wraps ``flat`` (shape (blocks.size,)) with the names of ``blocks``."""
        self.flat, self._blocks = flat, blocks

    def __getitem__(self, name: str) -> _View:
        """The writable view of block ``name`` (indexed like ``blocks[name]``)."""
        return _View(self.flat, self._blocks[name])


class Blocks:
    """The named index arrays of one flat vector (x, p or g) of length ``size``."""

    def __init__(self, entries: Mapping[str, list[_Entry]], size: int) -> None:
        """Index arrays from the registrations of each block (see :class:`NLPBuilder`)."""
        self.size = size
        self._entries = {name: tuple(es) for name, es in entries.items()}
        self._idx: dict[str, np.ndarray] = {}
        by_stage: dict[Hashable, list[np.ndarray]] = {}
        for name, es in self._entries.items():
            if es[0].stage is None:
                idx = es[0].indices()
            else:  # the entries share one shape: each is its offset plus the first's cells
                if any(e.shape != es[0].shape for e in es):
                    raise ValueError(f"block {name!r}: its stages' shapes differ "
                                     f"({sorted({e.shape for e in es})})")
                cells = _Entry(None, 0, es[0].shape).indices()
                offsets = np.fromiter((e.offset for e in es), dtype=int, count=len(es))
                idx = offsets.reshape((-1,) + (1,) * cells.ndim) + cells
                flat = offsets[:, None] + np.arange(cells.size)
                for e, row in zip(es, flat, strict=True):
                    by_stage.setdefault(e.stage, []).append(row)
            idx.flags.writeable = False
            self._idx[name] = idx
        self._by_stage = {stage: np.sort(np.concatenate(parts))
                          for stage, parts in by_stage.items()}

    @property
    def names(self) -> tuple[str, ...]:
        """Block names in registration order."""
        return tuple(self._idx)

    def __contains__(self, name: object) -> bool:
        """True if a block of that name exists."""
        return name in self._idx

    def __getitem__(self, name: str) -> np.ndarray:
        """Flat indices of block ``name``: shape (stages, *shape) if staged, else shape."""
        return self._idx[name]

    def stages(self, name: str) -> tuple:
        """Stage labels of block ``name``, one per row of its index array (() unstaged)."""
        es = self._entries[name]
        return () if es[0].stage is None else tuple(e.stage for e in es)

    def at(self, stage: Hashable) -> np.ndarray:
        """Flat indices of every block entry registered in ``stage``, in flat order."""
        return self._by_stage.get(stage, np.zeros(0, dtype=int)).copy()

    def grid(self, name: str, fill: int = -1) -> np.ndarray:
        """Index array of a block staged by integer (or integer-tuple) labels on a grid.

        Returns:
            Shape (max label + 1 per label dimension, *shape); stages the block was not
            registered in hold ``fill``.
        """
        keys = [s if isinstance(s, tuple) else (s,) for s in self.stages(name)]
        dims = tuple(max(key[i] for key in keys) + 1 for i in range(len(keys[0])))
        idx = self._idx[name]
        out = np.full(dims + idx.shape[1:], fill, dtype=int)
        for key, row in zip(keys, idx, strict=True):
            out[key] = row
        return out

    def zeros(self) -> dict[str, np.ndarray]:
        """A zero array per block, shaped like its index array (to fill, then pack)."""
        return {name: np.zeros(idx.shape) for name, idx in self._idx.items()}

    def pack(self, values: Mapping[str, np.ndarray]) -> np.ndarray:
        """The flat vector of named arrays (each broadcastable to its block's shape).

        Raises:
            KeyError: a block is missing or a name is unknown.
        """
        if set(values) != set(self._idx):
            raise KeyError(f"pack: missing {sorted(set(self._idx) - set(values))}, "
                           f"unknown {sorted(set(values) - set(self._idx))}")
        flat = np.zeros(self.size)
        for name, idx in self._idx.items():
            flat[idx] = values[name]
        return flat

    def unpack(self, flat: np.ndarray) -> dict[str, np.ndarray]:
        """Named arrays (copies) of a flat vector, shape (size,)."""
        flat = np.asarray(flat).ravel()
        return {name: flat[idx] for name, idx in self._idx.items()}

    def vector(self, fill: float = 0.0) -> NamedVector:
        """A new flat vector filled with ``fill``, addressed by block name."""
        return NamedVector(np.full(self.size, fill, dtype=float), self)


@dataclass(frozen=True)
class Bounds:
    """Bound vectors of one solve, filled by block name (``lbg["dynamics"][:] = 0``)."""

    lbx: NamedVector
    ubx: NamedVector
    lbg: NamedVector
    ubg: NamedVector

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The flat (lbx, ubx, lbg, ubg)."""
        return self.lbx.flat, self.ubx.flat, self.lbg.flat, self.ubg.flat


@dataclass(frozen=True)
class NLPLayout:
    """Where every named block sits in the flat x (variables), p and g (rows)."""

    x: Blocks
    p: Blocks
    g: Blocks

    def bounds(self) -> Bounds:
        """Unbounded bound vectors (-inf / +inf) to fill by name."""
        return Bounds(self.x.vector(-np.inf), self.x.vector(np.inf),
                      self.g.vector(-np.inf), self.g.vector(np.inf))

    def to_dict(self) -> dict:
        """JSON-ready registrations of x, p and g (:meth:`from_dict` rebuilds the layout)."""
        return {kind: {"size": blocks.size, "entries": {
            name: [[_label(e.stage), e.offset, list(e.shape)] for e in es]
            for name, es in blocks._entries.items()}}
            for kind, blocks in (("x", self.x), ("p", self.p), ("g", self.g))}

    @classmethod
    def from_dict(cls, data: dict) -> NLPLayout:
        """The layout of :meth:`to_dict`'s output.

        Raises:
            KeyError, TypeError, ValueError: ``data`` is not such an output.
        """
        def blocks(d: dict) -> Blocks:
            entries = {str(name): [_Entry(_stage(st), int(off), tuple(int(v) for v in shape))
                                   for st, off, shape in es]
                       for name, es in d["entries"].items()}
            return Blocks(entries, int(d["size"]))

        return cls(blocks(data["x"]), blocks(data["p"]), blocks(data["g"]))


def _label(stage: Hashable | None):
    """A stage label as JSON (tuples as lists)."""
    return list(stage) if isinstance(stage, tuple) else stage


def _stage(label) -> Hashable | None:
    """The stage label of :func:`_label`'s output."""
    if isinstance(label, list):
        return tuple(int(v) for v in label)
    if label is None or isinstance(label, int | str):
        return label
    raise TypeError(f"stage label {label!r}")


class _Flat:
    """The registrations of one flat vector while building."""

    def __init__(self) -> None:
        self.parts: list[ca.SX] = []
        self.entries: dict[str, list[_Entry]] = {}
        self._stages: dict[str, set] = {}  # the stages each block is registered in
        self.size = 0
        self.placed = 0  # entries registered by their place only (no expression)

    def add(self, name: str, stage: Hashable | None, expr: ca.SX | None,
            shape: tuple) -> None:
        entries = self.entries.setdefault(name, [])
        stages = self._stages.setdefault(name, set())
        if entries and (stage is None or entries[0].stage is None or stage in stages):
            raise ValueError(f"block {name!r} registered twice (stage {stage!r})")
        if entries and entries[0].shape != shape:
            raise ValueError(f"block {name!r}: shape {shape} != {entries[0].shape}")
        if (expr is None and self.parts) or (expr is not None and self.placed):
            raise ValueError(f"block {name!r}: rows made and rows placed in one vector")
        numel = math.prod(shape) if expr is None else expr.numel()
        if numel != math.prod(shape):
            raise ValueError(f"block {name!r}: {numel} entries for shape {shape}")
        entries.append(_Entry(stage, self.size, shape))
        stages.add(stage)
        if expr is None:
            self.placed += 1
        else:
            self.parts.append(expr if expr.size2() == 1 else ca.vec(expr))
        self.size += numel

    def flat(self) -> ca.SX:
        return ca.vertcat(*self.parts) if self.parts else ca.SX(0, 1)

    def blocks(self) -> tuple[ca.SX, Blocks]:
        return self.flat(), Blocks(self.entries, self.size)


class NLPBuilder:
    """Registers named blocks in flat-vector order and builds the NLP and its layout."""

    def __init__(self) -> None:
        """An empty NLP."""
        self._flat = {"x": _Flat(), "p": _Flat(), "g": _Flat()}
        self._stage: Hashable | None = None

    @contextmanager
    def stage(self, label: Hashable) -> Iterator[None]:
        """Blocks registered inside belong to stage ``label`` (an int or int tuple)."""
        outer, self._stage = self._stage, label
        try:
            yield
        finally:
            self._stage = outer

    def _symbol(self, kind: str, name: str, shape: Shape) -> ca.SX:
        shape = _shape(shape)
        if len(shape) > 2:
            raise ValueError(f"block {name!r}: at most 2 dimensions, got {shape}")
        label = name if self._stage is None else f"{name}_{self._stage}"
        sym = ca.SX.sym(label, *shape) if shape else ca.SX.sym(label)
        self._flat[kind].add(name, self._stage, sym, shape)
        return sym

    def variable(self, name: str, shape: Shape = ()) -> ca.SX:
        """Next decision-variable block; returns its symbol (shape () is a scalar)."""
        return self._symbol("x", name, shape)

    def parameter(self, name: str, shape: Shape = ()) -> ca.SX:
        """Next parameter block; returns its symbol (shape () is a scalar)."""
        return self._symbol("p", name, shape)

    def rows(self, name: str, expr, shape: Shape | None = None) -> None:
        """Next constraint-row block.

        Args:
            name: row-group name (e.g. ``"dynamics"``).
            expr: the rows: an SX expression (flattened column-major) or a list of them.
            shape: block shape; default (number of rows,); () for a single scalar row.
        """
        expr = ca.vertcat(*expr) if isinstance(expr, list | tuple) else expr
        self._flat["g"].add(name, self._stage, expr,
                            (expr.numel(),) if shape is None else _shape(shape))

    def place_rows(self, name: str, shape: Shape) -> None:
        """Next constraint-row block by its place only.

        The rows are made elsewhere, in the flat order of :meth:`layout`; an NLP with
        placed rows has no :meth:`build`.
        """
        self._flat["g"].add(name, self._stage, None, _shape(shape))

    def symbols(self) -> tuple[ca.SX, ca.SX]:
        """The flat (x, p) of the blocks registered so far."""
        return self._flat["x"].flat(), self._flat["p"].flat()

    def layout(self) -> NLPLayout:
        """The layout of the blocks registered so far."""
        return NLPLayout(*(Blocks(self._flat[k].entries, self._flat[k].size) for k in "xpg"))

    def build(self, f) -> tuple[dict, NLPLayout]:
        """The NLP ``{"x", "p", "f", "g"}`` with objective ``f``, and its layout.

        Raises:
            ValueError: a row block was registered by :meth:`place_rows`.
        """
        if self._flat["g"].placed:
            raise ValueError("build: rows registered by place_rows: make g from layout()")
        (x, lx), (p, lp), (g, lg) = (self._flat[k].blocks() for k in "xpg")
        return {"x": x, "p": p, "f": f, "g": g}, NLPLayout(lx, lp, lg)
