"""Figures of ``hmpc tube``: tube diameter versus time, margins versus MPC rate.

Drawn from arrays the command computes (no controller, no system): every bound's
diameter over time with Prop. 3's tau and the MPC periods marked, and the guard-avoid
offsets and input margins the tube implies per MPC rate (log x).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from hmpc_cli.figures.common import COLUMN_WIDTH_IN, figure_style, save_figure

__all__ = ["draw_diameters", "draw_margins", "draw_reality"]

_STYLE = {"trivial": ("#1f4e8c", "-", "trivial (Prop. 2)"),
          "ff_only": ("#d2691e", "--", "feed-forward only (Remark)"),
          "prop3": ("#2e8b57", "-", "Prop. 3: a(t)"),
          "kinematic": ("#8b008b", "-.", "kinematic: int diam T")}


#: values above this are off scale (Matplotlib's log axes overflow near 1e308)
OFF_SCALE = 1e100


def _plottable(values: np.ndarray) -> np.ndarray:
    """The values with NaN where not finite or off scale (not drawn)."""
    v = np.asarray(values, dtype=float)
    return np.where(np.isfinite(v) & (np.abs(v) <= OFF_SCALE), v, np.nan)


def _scale(ax, series: Iterable[np.ndarray]) -> bool:
    """Log y when some drawn value is positive, else linear; whether something is off scale."""
    vals = [np.asarray(v, dtype=float) for v in series]
    drawn = np.concatenate([_plottable(v) for v in vals]) if vals else np.zeros(0)
    if np.any(drawn > 0):
        ax.set_yscale("log")
    off = any(np.any(np.isinf(v) | (np.abs(v) > OFF_SCALE)) for v in vals)
    if off:
        ax.text(0.02, 0.02, "inf or > 1e100: not drawn", transform=ax.transAxes,
                ha="left", va="bottom", fontsize=6, color="0.4")
    return off


def draw_diameters(out_dir: Path, t: np.ndarray, curves: Mapping[str, np.ndarray],
                   tau: float | None, periods: Iterable[float], title: str,
                   formats: Iterable[str]) -> list[Path]:
    """Writes ``tube_diameter.<fmt>``: diam(t) per bound (log y when positive).

    Args:
        out_dir: existing output directory.
        t: times (K,) [s].
        curves: bound name (trivial, ff_only, prop3) -> diameters (K,) [state norm];
            NaN or inf where a bound does not hold or overflows.
        tau: Prop. 3's tau [s] (marked if finite), or None.
        periods: MPC periods [s] to mark.
        title: figure title.
        formats: output formats.

    Returns:
        The written paths.
    """
    import matplotlib.pyplot as plt

    with figure_style():
        fig, ax = plt.subplots(figsize=(COLUMN_WIDTH_IN, 2.4), layout="constrained")
        for name, values in curves.items():
            color, ls, label = _STYLE.get(name, ("k", ":", name))
            ax.plot(t, _plottable(values), color=color, linestyle=ls, label=label)
        _scale(ax, [v[~np.isnan(v)] for v in curves.values()])
        for p in periods:
            ax.axvline(p, color="0.8", linewidth=0.5, zorder=0)
        if tau is not None and np.isfinite(tau) and tau <= t[-1]:
            ax.axvline(tau, color="#2e8b57", linestyle=":", label=f"tau = {tau:.3g} s")
        if not any(np.any(np.nan_to_num(v, posinf=1.0) > 0) for v in curves.values()):
            ax.text(0.5, 0.5, "zero disturbance set: every tube is 0",
                    transform=ax.transAxes, ha="center")
        ax.set_xlabel("time since the last MPC solve t [s]")
        ax.set_ylabel("tube diameter [state norm]")
        ax.set_title(title)
        ax.legend(loc="best")
        return save_figure(fig, out_dir, "tube_diameter", formats)


def draw_margins(out_dir: Path, rates: np.ndarray, guards: Mapping[str, np.ndarray],
                 inputs: Mapping[str, np.ndarray], rate: float, title: str,
                 formats: Iterable[str]) -> list[Path]:
    """Writes ``tube_margins.<fmt>``: guard-avoid offsets and input margins vs MPC rate.

    Args:
        out_dir: existing output directory.
        rates: MPC rates (R,) [Hz] (log x).
        guards: guard name -> guard-avoid offset kappa(diam T(1/rate)) (R,) [NLP row
            units]; NaN where the guard's margin formula does not hold (not drawn).
        inputs: mode name -> input margin per side (R,) [input units].
        rate: the scenario's MPC rate [Hz] (marked).
        title: figure title.
        formats: output formats.

    Returns:
        The written paths.
    """
    import matplotlib.pyplot as plt

    with figure_style():
        fig, (ax_g, ax_u) = plt.subplots(1, 2, figsize=(2 * COLUMN_WIDTH_IN, 2.4),
                                         layout="constrained")
        for ax, series, ylabel in ((ax_g, guards, "guard-avoid offset kappa"),
                                   (ax_u, inputs, "input margin per side")):
            for name, values in series.items():
                ax.plot(rates, _plottable(values), label=name)
            ax.set_xscale("log")
            ax.set_xlim(rates.min(), rates.max())
            ax.axvline(rate, color="0.7", linestyle=":", zorder=0)
            _scale(ax, [v[~np.isnan(v)] for v in series.values()])
            ax.set_xlabel("MPC rate [Hz]")
            ax.set_ylabel(ylabel)
            if series:
                ax.legend(loc="best")
        fig.suptitle(title)
        return save_figure(fig, out_dir, "tube_margins", formats)


def _reality_panel(ax, periods: list[tuple[np.ndarray, np.ndarray]], t: np.ndarray,
                   curves: Mapping[str, np.ndarray], ylabel: str) -> None:
    """One panel of :func:`draw_reality`: the deviations (grey) under the bounds."""
    for i, (tau, dev) in enumerate(periods):
        ax.plot(tau, np.where(dev > 0, dev, np.nan), color="0.6", linewidth=0.6,
                marker=".", markersize=2, label="observed" if i == 0 else None)
    for name, values in curves.items():
        color, ls, label = _STYLE.get(name, ("k", ":", name))
        ax.plot(t, _plottable(values), color=color, linestyle=ls, label=label)
    _scale(ax, [v[~np.isnan(v)] for v in curves.values()] + [d[d > 0] for _, d in periods])
    ax.set_xlabel("time since the solve tau [s]")
    ax.set_ylabel(ylabel)
    ax.legend(loc="best")


def draw_reality(out_dir: Path, periods: Iterable[tuple[np.ndarray, np.ndarray]],
                 t: np.ndarray, curves: Mapping[str, np.ndarray], title: str,
                 formats: Iterable[str],
                 kinematic: Iterable[tuple[np.ndarray, np.ndarray]] = ()) -> list[Path]:
    """Writes ``tube_reality.<fmt>``: every period's deviation (grey) over the bounds.

    Args:
        out_dir: existing output directory.
        periods: per period (tau (K,) [s], deviation (K,) [state norm]).
        t: times since the solve (M,) [s] of the bound curves.
        curves: bound name -> bound (M,) [state norm] (NaN: not drawn); ``kinematic``
            goes to the second panel.
        title: figure title.
        formats: output formats.
        kinematic: per period (tau, deviation of the kinematic states): a second panel
            against the ``kinematic`` curve when given.

    Returns:
        The written paths.
    """
    import matplotlib.pyplot as plt

    periods, kinematic = list(periods), list(kinematic)
    state = {k: v for k, v in curves.items() if k != "kinematic"}
    panels = 2 if kinematic and "kinematic" in curves else 1
    with figure_style():
        fig, axes = plt.subplots(1, panels, figsize=(panels * COLUMN_WIDTH_IN, 2.4),
                                 layout="constrained", squeeze=False)
        _reality_panel(axes[0, 0], periods, t, state, "||x - x_plan|| [state norm]")
        if panels == 2:
            _reality_panel(axes[0, 1], kinematic, t, {"kinematic": curves["kinematic"]},
                           "kinematic states' deviation")
        fig.suptitle(title)
        return save_figure(fig, out_dir, "tube_reality", formats)
