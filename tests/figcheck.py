"""Legibility checks of a drawn Matplotlib figure: size, font, font sizes, overlapping text."""

from __future__ import annotations

import itertools

MIN_PT = 7.0


def _agg(fig):
    """The figure's Agg canvas (attached if the figure has none yet)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    return fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)


def _undrawn_tick_labels(fig) -> set[int]:
    """ids of tick labels whose tick lies outside its axis's view (Matplotlib skips them)."""
    from matplotlib.axes import Axes

    out = set()
    for ax in fig.findobj(Axes):  # insets (a colour bar) too
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            tol = 1e-9 * max(1.0, hi - lo)
            for tick in [*axis.get_major_ticks(), *axis.get_minor_ticks()]:
                if not lo - tol <= tick.get_loc() <= hi + tol:
                    out |= {id(tick.label1), id(tick.label2)}
    return out


def texts(fig) -> list:
    """The figure's drawn, non-empty text artists (titles, labels, ticks, legend, ...)."""
    from matplotlib.text import Text

    _agg(fig).draw()  # ticks and layout as saved
    skip = _undrawn_tick_labels(fig)
    return [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()
            and id(t) not in skip and (t.axes is None or t.axes.get_visible())]


def _boxes(fig, renderer) -> list:
    """(name, bbox) of tick labels, titles, axis labels and legend entries."""
    out = []
    for t in texts(fig):
        box = t.get_window_extent(renderer)
        if box.width > 0 and box.height > 0:
            out.append((repr(t.get_text()), box))
    return out


def overlaps(fig) -> list[tuple[str, str]]:
    """Pairs of text artists whose rendered boxes overlap (Agg canvas, shrunk by 0.5 px)."""
    renderer = _agg(fig).get_renderer()
    boxes = [(n, b.padded(-0.5)) for n, b in _boxes(fig, renderer)]
    return [(a, b) for (a, ba), (b, bb) in itertools.combinations(boxes, 2) if ba.overlaps(bb)]


def outside(fig) -> list[str]:
    """Text artists reaching past the figure's edges."""
    from matplotlib.transforms import Bbox

    renderer = _agg(fig).get_renderer()
    page = Bbox.from_bounds(0, 0, *fig.canvas.get_width_height()).padded(0.5)
    return [n for n, b in _boxes(fig, renderer)
            if not (page.contains(b.x0, b.y0) and page.contains(b.x1, b.y1))]


def assert_legible(fig, width: float, height: float) -> None:
    """Size as asked, STIX everywhere, text >= 7 pt, no overlapping or cut text."""
    from matplotlib import font_manager

    assert tuple(fig.get_size_inches()) == (width, height)
    for t in texts(fig):
        assert t.get_fontsize() >= MIN_PT, (t.get_text(), t.get_fontsize())
        font = font_manager.findfont(t.get_fontproperties(), fallback_to_default=False)
        assert "STIX" in font, (t.get_text(), font)
    assert not overlaps(fig), overlaps(fig)
    assert not outside(fig), outside(fig)
