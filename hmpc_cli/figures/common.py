"""Shared figure helpers: IEEE rc style, deterministic saving, sweep tables and run logs."""

from __future__ import annotations

import contextlib
import csv
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "COLUMN_WIDTH_IN", "FORMATS", "OKABE_ITO", "FigureInputError", "RunTrace", "TEXT_WIDTH_IN",
    "page_link",
    "check_size", "figure_style", "ieee_rc", "load_trace", "parse_bool", "parse_formats",
    "read_table", "resolve_log", "resolve_run_log", "resolve_table", "save_figure",
    "trace_of", "write_csv",
]

TEXT_WIDTH_IN = 7.16  # IEEE two-column: full text width (in)
COLUMN_WIDTH_IN = 3.5  # IEEE two-column: one column (in)
FORMATS = ("pdf", "svg", "png")
# Okabe-Ito colour-blind-safe palette (Okabe & Ito 2008); every series also has its own
# marker or line style, so the figures read in grey too.
OKABE_ITO = {"orange": "#E69F00", "sky_blue": "#56B4E9", "green": "#009E73",
             "yellow": "#F0E442", "blue": "#0072B2", "vermillion": "#D55E00",
             "purple": "#CC79A7", "black": "#000000"}
_TRUE = {"true", "1", "yes"}
_FALSE = {"false", "0", "no"}
# Fixed metadata per format: no dates, no version strings, so the bytes depend on the input only.
_METADATA: dict[str, dict[str, Any]] = {
    "pdf": {"Creator": "hmpc", "Producer": "hmpc", "CreationDate": None},
    "svg": {"Creator": "hmpc", "Date": None},
    "png": {"Software": "hmpc"},
}


class FigureInputError(ValueError):
    """Bad figure input (table, columns, logs, options); the message is one line."""


def ieee_rc(font_size: float = 8.0) -> dict[str, Any]:
    """Returns rcParams for IEEE two-column figures: Times-like 8 pt, thin lines, embeddable fonts.

    The font is STIX (Times-like, as IEEE's body text), text and mathtext alike; STIXGeneral
    ships with Matplotlib, so every machine draws the same glyphs (deterministic bytes).
    No text is smaller than 7 pt at print size.
    """
    return {
        "font.family": "serif",
        "font.serif": ["STIXGeneral"],
        "mathtext.fontset": "stix",
        "font.size": font_size,
        "axes.titlesize": font_size,
        "axes.labelsize": font_size,
        "xtick.labelsize": font_size,
        "ytick.labelsize": font_size,
        "legend.fontsize": max(font_size - 1, 7.0),
        "axes.linewidth": 0.6,
        "lines.linewidth": 0.7,
        "lines.markersize": 3.0,
        "patch.linewidth": 0.6,
        "xtick.major.width": 0.6,
        "ytick.major.width": 0.6,
        "xtick.minor.width": 0.4,
        "ytick.minor.width": 0.4,
        "xtick.major.size": 2.5,
        "ytick.major.size": 2.5,
        "xtick.direction": "in",
        "ytick.direction": "in",
        "axes.titlepad": 3.0,
        "axes.labelpad": 2.0,
        "legend.frameon": False,
        "legend.handlelength": 1.6,
        "legend.borderaxespad": 0.3,
        "pdf.fonttype": 42,  # TrueType, not Type 3: accepted by IEEE PDF eXpress
        "ps.fonttype": 42,
        "svg.fonttype": "path",
        "svg.hashsalt": "hmpc",  # fixed element ids in SVG output
        "savefig.bbox": None,  # keep the exact figure size
        "savefig.dpi": 300,
        "figure.dpi": 100,
    }


@contextlib.contextmanager
def figure_style():
    """Context manager: Matplotlib defaults + :func:`ieee_rc` inside the block.

    The user's matplotlibrc does not leak in and the previous settings are restored on
    exit; pyplot uses the non-interactive Agg canvas.
    """
    import matplotlib as mpl

    with mpl.rc_context():
        mpl.rcdefaults()
        mpl.rcParams.update(ieee_rc())
        mpl.rcParams["backend"] = "Agg"
        yield


def check_size(width: float, height: float) -> None:
    """Raises FigureInputError unless both sizes lie in [0.5, 20] inches."""
    if not (0.5 <= width <= 20 and 0.5 <= height <= 20):
        raise FigureInputError(f"figure size {width} x {height} in is out of range [0.5, 20]")


def write_csv(path: Path, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Writes a CSV table atomically (temporary file, then rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(header)
            w.writerows(rows)
        tmp.replace(path)
    except OSError as exc:
        raise FigureInputError(f"{path}: cannot write ({exc})") from None


def resolve_run_log(path: str | Path) -> Path:
    """The log itself, or run.mcap when ``path`` is a run directory holding one."""
    path = Path(path)
    return path / "run.mcap" if path.is_dir() and (path / "run.mcap").is_file() else path


def parse_formats(text: str | Iterable[str]) -> tuple[str, ...]:
    """Parses "pdf,svg,png" (or a sequence) into distinct known formats, in the given order."""
    items = text.split(",") if isinstance(text, str) else list(text)
    out: list[str] = []
    for item in (s.strip().lower().lstrip(".") for s in items):
        if not item:
            continue
        if item not in FORMATS:
            raise FigureInputError(f"unknown format {item!r} (choose from {', '.join(FORMATS)})")
        if item not in out:
            out.append(item)
    if not out:
        raise FigureInputError(f"no output format given (choose from {', '.join(FORMATS)})")
    return tuple(out)


def make_out_dir(out: Path) -> Path:
    """Creates the output directory ``out`` (and parents); returns it.

    Raises:
        FigureInputError: it cannot be created.
    """
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FigureInputError(f"{out}: cannot create the output directory ({exc})") from None
    return out


def save_figure(fig: Any, out_dir: Path, stem: str, formats: Iterable[str],
                dpi: int = 300, close: bool = True) -> list[Path]:
    """Saves ``fig`` as out_dir/stem.<fmt> per format, with fixed metadata.

    The same input gives the same bytes; each file is written to a temporary name and
    renamed, so no half-written figure is left behind.

    Args:
        fig: a Matplotlib figure.
        out_dir: existing output directory.
        stem: file name without extension.
        formats: output formats (see :func:`parse_formats`).
        dpi: resolution of raster formats [dots per inch].
        close: close a pyplot-managed figure afterwards, whatever happens.

    Returns:
        The written paths, in the order of ``formats``.

    Raises:
        FigureInputError: a file cannot be written.
    """
    paths = []
    try:
        for fmt in formats:
            path = Path(out_dir) / f"{stem}.{fmt}"
            tmp = path.with_name(f".{path.name}.tmp")
            fig.savefig(tmp, format=fmt, dpi=dpi, metadata=_METADATA[fmt])
            os.replace(tmp, path)  # never leave a half-written figure behind
            paths.append(path)
    except OSError as exc:
        raise FigureInputError(f"{out_dir}: cannot write the figure ({exc})") from None
    finally:
        if close and getattr(fig.canvas, "manager", None) is not None:
            import matplotlib.pyplot as plt  # only pyplot figures have a manager

            plt.close(fig)
    return paths


def sweep_spec(directory: str | Path) -> dict:
    """The sweep's own file as it ran (its output directory's ``sweep.toml``; {} if none)."""
    import tomllib

    try:
        return tomllib.loads((Path(directory) / "sweep.toml").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def resolve_table(path: str | Path) -> Path:
    """The table itself, or results.csv when `path` is a sweep directory holding one."""
    path = Path(path)
    if path.is_dir() and (path / "results.csv").is_file():
        return path / "results.csv"
    return path


def read_table(path: Path, required: Iterable[str]) -> list[dict[str, str]]:
    """Reads a CSV table with a header; checks it exists, has rows and the `required` columns."""
    path = Path(path)
    if not path.is_file():
        raise FigureInputError(f"{path}: no such table")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            columns = list(reader.fieldnames or [])
            rows = [dict(r) for r in reader]
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise FigureInputError(f"{path}: cannot read table ({exc})") from None
    missing = [c for c in required if c not in columns]
    if missing:
        have = ", ".join(columns) if columns else "none"
        raise FigureInputError(f"{path}: missing column(s) {', '.join(missing)} (has: {have})")
    if not rows:
        raise FigureInputError(f"{path}: table has no rows")
    return rows


def parse_bool(value: str | None, where: str) -> bool:
    """Parses a table cell like True/False (also true/1/yes, false/0/no)."""
    text = (value or "").strip().lower()
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise FigureInputError(f"{where}: expected True or False, got {value!r}")


def resolve_log(table_path: Path, log: str | None, where: str) -> Path:
    """Resolves a log path relative to the table's directory; checks that the file exists."""
    text = (log or "").strip()
    if not text:
        raise FigureInputError(f"{where}: empty log path")
    path = Path(text)
    if not path.is_absolute():
        path = Path(table_path).parent / path
    if not path.is_file():
        raise FigureInputError(f"{where}: log {path} does not exist")
    return path


@dataclass
class RunTrace:
    """Positions of one recorded run: `t` (s), `xy` (n x 2, NaN where not finite), run info."""

    path: Path
    t: np.ndarray
    xy: np.ndarray
    scenario: dict = field(default_factory=dict)
    logged_success: bool | None = None  # the log's own /run/summary verdict, if any
    complete: bool = True
    damage: str = ""  # why reading stopped at a damaged chunk ('' if it did not)
    geometry: dict = field(default_factory=dict)  # the log's geometry (loggeometry)

    @property
    def system(self) -> dict:
        """The scenario's system parameters (radius, guards, goal, ...)."""
        return dict(self.scenario.get("system") or {})


def _num(v: Any) -> float:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else math.nan


def load_trace(path: Path) -> RunTrace:
    """Reads a run log's positions in its drawing plane from /sim/state, events spliced in.

    The plane is the log geometry's ``plane`` (two state names; default the first two
    states). The exact pre- and post-reset positions of /sim/event are inserted at the
    event times, so drawn bounces touch the guard instead of cutting the corner between
    logged samples.
    """
    from hmpc_cli.rundata import read_run

    try:
        run = read_run(path)
    except ValueError as exc:
        raise FigureInputError(f"{path}: cannot read log ({exc})") from None
    return trace_of(run, Path(path))


def trace_of(run: Any, path: Path) -> RunTrace:
    """The positions of a run already read by ``read_run``, as :func:`load_trace` gives them."""
    plane = list(run.geometry.get("plane") or ())
    i, j = (run.state_names.index(plane[0]), run.state_names.index(plane[1])) \
        if len(plane) == 2 and set(plane) <= set(run.state_names) else (0, 1)
    points: list[tuple[float, int, int, float, float]] = []  # (t, kind, seq, a, b)
    if run.x.shape[1] > max(i, j):
        points += [(float(t), 1, k, _num(x[i]), _num(x[j]))
                   for k, (t, x) in enumerate(zip(run.t, run.x, strict=True))]
    if not points:
        raise FigureInputError(f"{path}: log has no /sim/state positions")
    for k, ev in enumerate(run.events):
        for m, x in enumerate((ev.x_before, ev.x_after)):
            if len(x) > max(i, j) and math.isfinite(ev.t):
                points.append((ev.t, 0, 2 * k + m, _num(x[i]), _num(x[j])))
    points.sort(key=lambda p: (p[0], p[1], p[2]))
    arr = np.array([(p[0], p[3], p[4]) for p in points], dtype=float)
    ok = run.summary.get("success") if run.summary else None
    return RunTrace(Path(path), arr[:, 0], arr[:, 1:3], run.scenario,
                    ok if isinstance(ok, bool) else None, run.complete, run.damage,
                    dict(run.geometry))


def page_link(path: Path, base: Path) -> str:
    """``path`` as a link on a page in ``base``: relative if inside it, else absolute."""
    try:
        return Path(path).resolve().relative_to(Path(base).resolve()).as_posix()
    except ValueError:
        return Path(path).resolve().as_posix()
