"""Shared figure helpers: IEEE rc style, sizes, formats, deterministic saving, page links."""

from __future__ import annotations

import contextlib
import csv
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any


from hmpc_cli.analysis.tables import FigureInputError

__all__ = [
    "COLUMN_WIDTH_IN", "FORMATS", "GIF_DPI", "OKABE_ITO", "TEXT_WIDTH_IN", "check_outputs",
    "check_size", "figure_style", "ieee_rc", "page_link", "parse_formats", "save_figure",
    "save_gif", "write_csv",
]

TEXT_WIDTH_IN = 7.16  # IEEE two-column: full text width (in)
COLUMN_WIDTH_IN = 3.5  # IEEE two-column: one column (in)
GIF_DPI = 150  # animations' resolution (dots per inch): 750 pixels across 5 in
FORMATS = ("pdf", "svg", "png")
# Okabe-Ito colour-blind-safe palette (Okabe & Ito 2008); every series also has its own
# marker or line style, so the figures read in grey too.
OKABE_ITO = {"orange": "#E69F00", "sky_blue": "#56B4E9", "green": "#009E73",
             "yellow": "#F0E442", "blue": "#0072B2", "vermillion": "#D55E00",
             "purple": "#CC79A7", "black": "#000000"}
# Fixed metadata per format: no dates, no version strings, so the bytes depend on the input only.
_METADATA: dict[str, dict[str, Any]] = {
    "pdf": {"Creator": "hmpc", "Producer": "hmpc", "CreationDate": None},
    "svg": {"Creator": "hmpc", "Date": None},
    "png": {"Software": "hmpc"},
}


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
    from hmpc_cli.core.paths import atomic_file

    path = Path(path)
    try:
        with atomic_file(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f, lineterminator="\n")
            w.writerow(header)
            w.writerows(rows)
    except OSError as exc:
        raise FigureInputError(f"{path}: cannot write ({exc})") from None


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


def check_outputs(out_dir: Path, names: Iterable[str]) -> None:
    """Refuses, before anything is written, an output file name held by a directory.

    Raises:
        FigureInputError: ``out_dir/<name>`` is a directory (it would be written after
            the command's other files, leaving them half a set).
    """
    for name in names:
        if (Path(out_dir) / name).is_dir():
            raise FigureInputError(f"{Path(out_dir) / name}: is a directory, where this "
                                   "command writes a file: remove it or choose another "
                                   "output directory")


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
    from matplotlib.layout_engine import PlaceHolderLayoutEngine

    from hmpc_cli.core.paths import atomic_file

    formats = list(formats)  # read twice
    check_outputs(out_dir, (f"{stem}.{fmt}" for fmt in formats))
    paths = []
    # the layout engine run once (each savefig ran it again), every format drawn with its
    # layout and from the same axes' positions: a draw moves fixed-aspect axes, so a PNG
    # saved after the PDF differed from one saved alone
    engine = fig.get_layout_engine()
    if engine is not None and not isinstance(engine, PlaceHolderLayoutEngine):
        engine.execute(fig)
        fig.set_layout_engine("none")
    start = [(ax, ax.get_position(original=True).frozen(), ax.get_position().frozen())
             for ax in fig.get_axes()]
    try:
        for fmt in formats:
            for ax, original, active in start:
                ax._set_position(original, which="original")
                ax._set_position(active, which="active")
            path = Path(out_dir) / f"{stem}.{fmt}"
            with atomic_file(path) as tmp:  # never leave a half-written figure behind
                fig.savefig(tmp, format=fmt, dpi=dpi, metadata=_METADATA[fmt])
            paths.append(path)
    except OSError as exc:
        raise FigureInputError(f"{out_dir}: cannot write the figure ({exc})") from None
    finally:
        if engine is not None:
            fig.set_layout_engine(engine)
        if close and getattr(fig.canvas, "manager", None) is not None:
            import matplotlib.pyplot as plt  # only pyplot figures have a manager

            plt.close(fig)
    return paths


def save_gif(fig: Any, draw: Callable[[Any], object], frames: Iterable[Any], path: Path,
             fps: float, dpi: int = GIF_DPI) -> Path:
    """Writes ``fig`` after ``draw(f)`` for each f of ``frames`` as a looping GIF.

    The file is the one Matplotlib's ``Animation.save`` writes with its ``PillowWriter`` at
    ``dpi`` [dots per inch], ``fps`` frames per second of playback, but a figure without a
    layout engine is drawn once per frame, not twice (the second draw places the axes of a
    constrained layout). It is written under a temporary name and renamed: ``draw``
    raising (a stop signal) or a failed write leaves no file behind.

    Raises:
        ValueError: no frames.
        OSError: the file cannot be written.
    """
    import io

    from PIL import Image

    from hmpc_cli.core.paths import atomic_file

    layout = fig.get_layout_engine() is not None
    w, h = fig.get_size_inches()  # in pixels as the canvas rounds them (PillowWriter's)
    size = int(w * dpi + 1e-8), int(h * dpi + 1e-8)
    images = []
    for f in frames:
        draw(f)
        if layout:
            fig.canvas.draw()
        buf = io.BytesIO()
        fig.savefig(buf, format="rgba", dpi=dpi)
        if len(buf.getbuffer()) != 4 * size[0] * size[1]:
            raise RuntimeError(f"{path}: a frame of {len(buf.getbuffer())} bytes is not "
                               f"{size[0]} x {size[1]} RGBA pixels")
        im = Image.frombuffer("RGBA", size, buf.getbuffer(), "raw", "RGBA", 0, 1)
        # opaque frames as RGB, which Pillow turns into a palette better (as PillowWriter)
        images.append(im if im.getextrema()[3][0] < 255 else im.convert("RGB"))
    if not images:
        raise ValueError(f"{path}: an animation needs at least one frame")
    with atomic_file(path) as tmp:
        images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:],
                       duration=int(1000 / fps), loop=0)
    return Path(path)


def page_link(path: Path, base: Path) -> str:
    """``path`` as a link on a page in ``base``: relative if inside it, else absolute."""
    try:
        return Path(path).resolve().relative_to(Path(base).resolve()).as_posix()
    except ValueError:
        return Path(path).resolve().as_posix()


def static_polylines(geo) -> list[tuple[Any, Any]]:
    """A logged geometry's static polylines as (a (K,), b (K,)) [m], closed ones closed.

    ``geo``: a :class:`~hmpc_cli.log.geometry.GeometryRec` (None: no polylines).
    """
    import numpy as np

    out = []
    for line in geo.static if geo is not None else ():
        a, b = np.asarray(line.a, dtype=float), np.asarray(line.b, dtype=float)
        if a.size >= 2 and a.size == b.size:
            if line.closed:
                a, b = np.append(a, a[0]), np.append(b, b[0])
            out.append((a, b))
    return out
