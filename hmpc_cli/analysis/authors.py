"""The authors' Figure 3 trajectories (their reference data's CSV files) and their contacts.

Each CSV holds one panel: a column ``t`` [s] (uniform times on [0, 3]), then per trial the
ball centre's ``<trial>_x`` and ``<trial>_y`` [m] (``trial1`` .. ``trial10``, ``nominal``).
The files name no contacts; :func:`contacts` finds them in the positions:

* **floor / wall**: a sample k outside the circle where y (floor) or x (wall) has a local
  minimum (v_k <= v_k-1, v_k < v_k+1) with a kink, a second difference
  (v_k+1 - 2 v_k + v_k-1) / dt^2 above :data:`KINK` (50 m/s^2), within :data:`REACH` of the
  guard and inside its activity region. Outside the circle the ball can accelerate away
  from a wall only by the disturbance and drag (|w| <= 10 m/s^2, less than g for the
  floor), so a smooth minimum is never that sharp: on the authors' data every smooth
  minimum is below 9 m/s^2 and every bounce above 280 m/s^2. The contact time is the
  descending side (samples k-2, k-1) extrapolated to the guard, within [t_k-1, t_k+1].
* **circle_in / circle_out**: |p - c| crossing the circle's radius between two samples
  (time interpolated linearly); a crossing shorter than one sample step is not seen.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["KINK", "PANEL_FILES", "REACH", "AuthorsTrace", "BallGeometry", "Contact",
           "circle_entry", "contacts", "end_distance", "read_authors", "read_panels"]

#: the authors' CSV file per Figure 3 panel label (hmpc's sweep labels)
PANEL_FILES = {"10 Hz fixed": "fig3_left_10hz_fixed.csv",
               "20 Hz fixed": "fig3_middle_20hz_fixed.csv",
               "10 Hz replan": "fig3_right_10hz_hybrid.csv",
               "100 Hz fixed": "fig3_extra_100hz_fixed.csv"}
KINK = 50.0  # [m/s^2] second difference above which a local minimum is a bounce
REACH = 0.25  # [m] largest distance of a bounce's lowest sample from its guard


@dataclass(frozen=True)
class BallGeometry:
    """The ball's guards: radius r [m], circle centre (2,) and radius [m], activity ranges."""

    radius: float = 0.1
    centre: tuple[float, float] = (3.0, 3.0)
    circle_radius: float = 1.0
    floor_extent: tuple[float, float] = (0.0, 8.0)
    wall_extent: tuple[float, float] = (0.0, 8.0)

    @classmethod
    def from_params(cls, params: Mapping) -> BallGeometry:
        """From a ball's ``[system]`` parameters (missing keys: the reference's values)."""
        d = cls()

        def pair(key: str, default: tuple[float, float]) -> tuple[float, float]:
            v = params.get(key)
            return (float(v[0]), float(v[1])) if v is not None else default

        return cls(float(params.get("radius", d.radius)), pair("circle_center", d.centre),
                   float(params.get("circle_radius", d.circle_radius)),
                   pair("floor_extent", d.floor_extent), pair("wall_extent", d.wall_extent))


@dataclass(frozen=True)
class Contact:
    """A guard event: time [s] and guard name (floor, wall, circle_in, circle_out)."""

    t: float
    guard: str


@dataclass(frozen=True)
class AuthorsTrace:
    """One trial of the authors' data: label, times t (K,) [s], ball centre xy (K, 2) [m]."""

    label: str
    t: np.ndarray
    xy: np.ndarray


def _bounces(t: np.ndarray, v: np.ndarray, other: np.ndarray, outside: np.ndarray,
             level: float, extent: tuple[float, float], name: str) -> list[Contact]:
    """Kinked local minima of v (K,) near ``level`` [m] with ``other`` inside ``extent``."""
    dt = float(t[1] - t[0])
    out = []
    for k in range(1, len(t) - 1):
        if not (v[k] <= v[k - 1] and v[k] < v[k + 1] and outside[k]):
            continue
        if (v[k + 1] - 2 * v[k] + v[k - 1]) / dt**2 <= KINK or v[k] - level > REACH:
            continue
        if not extent[0] <= other[k] <= extent[1]:
            continue
        tc = float(t[k])
        if k >= 2 and v[k - 1] < v[k - 2]:  # extrapolate the way down to the guard
            speed = (v[k - 2] - v[k - 1]) / dt
            tc = float(np.clip(t[k - 1] + (v[k - 1] - level) / speed, t[k - 1], t[k + 1]))
        out.append(Contact(tc, name))
    return out


def _crossings(t: np.ndarray, r: np.ndarray, radius: float) -> list[Contact]:
    """circle_in / circle_out where the distance r (K,) [m] crosses ``radius``."""
    inside = r <= radius
    out = []
    for k in np.flatnonzero(inside[1:] != inside[:-1]):
        s = (r[k] - radius) / (r[k] - r[k + 1]) if r[k] != r[k + 1] else 0.0
        out.append(Contact(float(t[k] + s * (t[k + 1] - t[k])),
                           "circle_in" if inside[k + 1] else "circle_out"))
    return out


def contacts(t: np.ndarray, xy: np.ndarray, geo: BallGeometry = BallGeometry()) -> list[Contact]:
    """The guard events seen in sampled positions t (K,) [s], xy (K, 2) [m], in time order."""
    t, xy = np.asarray(t, dtype=float), np.asarray(xy, dtype=float)
    if len(t) < 3:
        return []
    r = np.hypot(xy[:, 0] - geo.centre[0], xy[:, 1] - geo.centre[1])
    outside = r > geo.circle_radius
    found = (_bounces(t, xy[:, 1], xy[:, 0], outside, geo.radius, geo.floor_extent, "floor")
             + _bounces(t, xy[:, 0], xy[:, 1], outside, geo.radius, geo.wall_extent, "wall")
             + _crossings(t, r, geo.circle_radius))
    return sorted(found, key=lambda c: c.t)


def circle_entry(t: np.ndarray, xy: np.ndarray, geo: BallGeometry = BallGeometry()
                 ) -> float | None:
    """The first time [s] with |p - c| <= the circle's radius (None: never)."""
    r = np.hypot(np.asarray(xy)[:, 0] - geo.centre[0], np.asarray(xy)[:, 1] - geo.centre[1])
    hit = np.flatnonzero(r <= geo.circle_radius)
    return float(np.asarray(t)[hit[0]]) if hit.size else None


def _trial_label(column: str) -> str:
    """``trial3`` -> ``trial 3``; ``nominal`` stays."""
    return f"trial {column[5:]}" if column.startswith("trial") else column


def read_authors(path: Path) -> dict[str, AuthorsTrace]:
    """The trials of one CSV by hmpc's trial label (``trial 1`` .. ``trial 10``, ``nominal``).

    Raises:
        ValueError: unreadable file, no ``t`` column, a trial without both coordinates,
            or a non-finite or non-increasing time (one line saying which).
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise ValueError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if not rows or rows[0][:1] != ["t"]:
        raise ValueError(f"{path}: not the authors' Figure 3 data (no 't' column first)")
    head = rows[0]
    try:
        data = np.array([[float(v) for v in row] for row in rows[1:] if row], dtype=float)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if data.ndim != 2 or data.shape[1] != len(head) or len(data) < 3:
        raise ValueError(f"{path}: need at least 3 rows of {len(head)} numbers")
    t = data[:, 0]
    if not (np.isfinite(data).all() and np.all(np.diff(t) > 0)):
        raise ValueError(f"{path}: non-finite values or times not increasing")
    stems = list(dict.fromkeys(h[:-2] for h in head[1:] if h.endswith(("_x", "_y"))))
    out = {}
    for stem in stems:
        if f"{stem}_x" not in head or f"{stem}_y" not in head:
            raise ValueError(f"{path}: {stem} lacks its _x or _y column")
        xy = data[:, [head.index(f"{stem}_x"), head.index(f"{stem}_y")]]
        out[_trial_label(stem)] = AuthorsTrace(_trial_label(stem), t, xy)
    return out


def read_panels(directory: Path) -> dict[str, dict[str, AuthorsTrace]]:
    """Every panel of :data:`PANEL_FILES` found in ``directory`` (ValueError: a bad file)."""
    directory = Path(directory)
    return {panel: read_authors(directory / name) for panel, name in PANEL_FILES.items()
            if (directory / name).is_file()}


def end_distance(xy: np.ndarray, geo: BallGeometry = BallGeometry()) -> float:
    """Distance [m] of the last position (2,) from the circle's centre."""
    p = np.asarray(xy)[-1]
    return math.hypot(float(p[0]) - geo.centre[0], float(p[1]) - geo.centre[1])
