"""Figure 3 beside the authors' data: the per-trial table, the reasons, the overlays."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from figcheck import assert_legible
from hmpc_cli.analysis.authors import AuthorsTrace, Contact, read_panels
from hmpc_cli.analysis.fig3compare import Side, TrialComparison, compare_sweep, sequence_text
from hmpc_cli.figures.common import TEXT_WIDTH_IN, figure_style
from hmpc_cli.run.runner import prepare, run_to_log
from hmpc_cli.run.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
BALL = ROOT / "scenarios" / "ball.toml"
SHORT = ["sim.duration=0.6", "mpc.horizon=1.0"]  # wall, floor, circle: all before 0.6 s


def _run(out: Path, overrides: list[str]) -> bool:
    """A short real ball run logged to out/run.mcap; its success."""
    sc, _ = load_scenario(BALL, [*SHORT, *overrides])
    out.mkdir(parents=True)
    return run_to_log(prepare(sc), out / "run.mcap").success


def _authors_csv(path: Path, trials: dict[str, np.ndarray], t: np.ndarray) -> None:
    """An authors'-style CSV: t, then <trial>_x, <trial>_y per trial (xy (K, 2))."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", *(f"{k}_{a}" for k in trials for a in "xy")])
        for i, ti in enumerate(t):
            w.writerow([f"{ti:.5f}", *(f"{xy[i, j]:.5f}" for xy in trials.values()
                                       for j in range(2))])


@pytest.mark.slow  # two 0.6 s ball runs (one NLP build): about 6-10 s
def test_per_trial_rows_from_small_real_runs(tmp_path):
    from hmpc_cli.log.rundata import read_run

    ok = {"nominal": _run(tmp_path / "nominal", ['disturbance.kind="none"']),
          "trial 1": _run(tmp_path / "trial1", ['disturbance.kind="paper_fig3"',
                                                "disturbance.trial=1"])}
    with open(tmp_path / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["controller", "disturbance", "success", "log"])
        w.writerow(["10 Hz fixed", "trial 1", ok["trial 1"], "trial1/run.mcap"])
        w.writerow(["10 Hz fixed", "nominal", ok["nominal"], "nominal/run.mcap"])
    # the authors: our nominal path resampled as they sampled theirs; their trial 1 never
    # leaves the start (so it fails)
    run = read_run(tmp_path / "nominal" / "run.mcap")
    t = np.linspace(0.0, 0.6, 80)
    mine = np.column_stack([np.interp(t, run.t, run.x[:, i]) for i in range(2)])
    _authors_csv(tmp_path / "fig3_left_10hz_fixed.csv",
                 {"trial1": np.tile([1.0, 1.0], (80, 1)), "nominal": mine}, t)
    rows = compare_sweep(tmp_path / "results.csv", read_panels(tmp_path))
    assert [(r.panel, r.trial) for r in rows] == [("10 Hz fixed", "nominal"),
                                                  ("10 Hz fixed", "trial 1")]
    nom, tr1 = rows
    events = [e.guard_name for e in run.events]
    assert events == ["wall", "floor", "circle_in"]  # hmpc's short plan, flown
    assert [c.guard for c in nom.ours.contacts] == events
    assert nom.same_sequence and nom.first_difference == "" and nom.why == ""
    assert nom.end_gap < 0.02 and nom.ours.entry == pytest.approx(nom.theirs.entry, abs=0.01)
    assert [c.guard for c in nom.facts.plan] == events  # the first accepted plan
    assert tr1.theirs.contacts == () and tr1.theirs.entry is None and not tr1.theirs.success
    assert tr1.ours.success and not tr1.same_sequence
    assert tr1.first_difference.startswith("contact 1: ours wall at 0.1")
    assert tr1.first_difference.endswith(", theirs none")
    assert "theirs never entered the circle" in tr1.why
    assert "their undisturbed run's contact 1 (wall at 0.1" in tr1.why
    assert "same planned sequence" in tr1.why  # their nominal contacts = our plan here


def _side(xy: np.ndarray, ok: bool, cs=()) -> Side:
    t = np.linspace(0.0, 3.0, len(xy))
    return Side(tuple(cs), None, xy[-1], ok, t, xy)


def test_overlay_figure_is_legible_at_text_width():
    from hmpc_cli.figures.fig3overlay import HEIGHT_PER_ROW_IN, overlay_figure

    s = np.linspace(0.0, 1.0, 200)[:, None]
    from hmpc_cli.log.geometry import GeometryRec, PolylineRec

    circle = np.linspace(0, 6.2, 40)
    geometry = GeometryRec((), (3.0, 3.0), (
        PolylineRec("floor", (0.0, 8.0), (0.0, 0.0), False),
        PolylineRec("wall", (0.0, 0.0), (0.0, 8.0), False),
        PolylineRec("circle", tuple(3 + np.cos(circle)), tuple(3 + np.sin(circle)), True)),
        (), ())
    rows = [TrialComparison("10 Hz fixed", label, _side((1 - s) * [1, 1] + s * [3, 3], True),
                            None, _side((1 - s) * [1, 1] + s * [0.2, 0.3], k != 5), (), "",
                            geometry)
            for k, label in enumerate(["nominal", *(f"trial {i}" for i in range(1, 11))])]
    with figure_style():
        fig = overlay_figure(rows, "reference mode, 10 Hz fixed")
        assert_legible(fig, TEXT_WIDTH_IN, 3 * HEIGHT_PER_ROW_IN + 0.2)
        titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
        assert titles[5] == "trial 5\nhmpc ok, authors failed"


def test_sequence_text_folds_repeats():
    cs = [Contact(0.1 * k, g) for k, g in enumerate(
        ["floor", "wall", "wall", "floor", "floor", "floor", "circle_in"])]
    assert sequence_text(cs) == "floor, wall x2, floor x3, circle_in"
    assert sequence_text([]) == "none"


def test_authors_trace_rows_without_our_log_keep_theirs(tmp_path):
    t = np.linspace(0.0, 3.0, 50)
    xy = np.column_stack([np.linspace(1, 3, 50), np.linspace(1, 3, 50)])
    with open(tmp_path / "results.csv", "w", newline="") as f:
        f.write("controller,disturbance,success,log\n10 Hz fixed,nominal,true,missing.mcap\n")
    rows = compare_sweep(tmp_path / "results.csv",
                         {"10 Hz fixed": {"nominal": AuthorsTrace("nominal", t, xy)}})
    assert rows[0].ours is None and "does not exist" in rows[0].note
    assert rows[0].theirs.success and rows[0].same_sequence is None and rows[0].why == ""


@pytest.mark.slow  # the two short runs again, then Figure 3, the overlay and the page
def test_report_page_tables_every_trial_beside_the_authors(tmp_path):
    from hmpc_cli.report.page import ReportInputs, write_report
    from hmpc_cli.log.rundata import read_run

    sweep = tmp_path / "sweep"
    ok = _run(sweep / "nominal", ['disturbance.kind="none"'])
    with open(sweep / "results.csv", "w", newline="") as f:
        f.write(f"controller,disturbance,success,log\n10 Hz fixed,nominal,{ok},"
                "nominal/run.mcap\n")
    run = read_run(sweep / "nominal" / "run.mcap")
    t = np.linspace(0.0, 0.6, 80)
    mine = np.column_stack([np.interp(t, run.t, run.x[:, i]) for i in range(2)])
    authors = tmp_path / "authors"
    authors.mkdir()
    # theirs: our path backwards (ends at the start: failed)
    _authors_csv(authors / "fig3_left_10hz_fixed.csv", {"nominal": mine[::-1]}, t)
    page = write_report(tmp_path / "results", ReportInputs(
        None, None, None, None, sweep, None, authors), "hmpc report").read_text()
    assert "| controller | paper | authors' data | reference mode |" in page
    assert "| 10 Hz fixed | 9/11 | 0/1 (nominal) | 1/1 |" in page
    assert "- **10 Hz fixed, nominal**: plans differ (ours: wall, floor, circle_in, 3 " in page
    assert "theirs entered at 0.00 s, left at 0.05 s" in page  # it starts inside
    end = run.x[-1]
    assert (f"| 10 Hz fixed | nominal | wall, floor, circle_in | "
            f"{run.events[-1].t:.2f} | ({end[0]:.2f}, {end[1]:.2f}) | yes | ") in page
    assert "![reference mode, 10 Hz fixed](report/overlay/overlay_reference_10_Hz_fixed.png)" \
        in page
    assert (tmp_path / "results" / "report" / "overlay" / "overlay_reference_10_Hz_fixed.png"
            ).is_file()


def test_agreement_counts_contact_times_and_the_whole_path():
    """Same guards but a contact 40 ms late is not the same timed sequence; the path
    deviation sees paths apart even when the end points meet."""
    from hmpc_cli.analysis.fig3compare import CONTACT_TOL

    t = np.linspace(0.0, 3.0, 301)
    line = np.column_stack([1 + 2 * t / 3, 1 + 2 * t / 3])  # (1, 1) -> (3, 3)
    bulge = line + np.column_stack([np.zeros_like(t), np.sin(np.pi * t / 3)])  # 1 m off
    ours = Side((Contact(0.24, "floor"), Contact(0.34, "wall")), 2.0, line[-1], True, t, line)
    late = Side((Contact(0.24, "floor"), Contact(0.34 + CONTACT_TOL + 0.01, "wall")), 2.0,
                bulge[-1], True, t, bulge)
    near = Side((Contact(0.25, "floor"), Contact(0.36, "wall")), 2.0, line[-1], True, t, line)
    far = TrialComparison("10 Hz fixed", "trial 1", ours, None, late)
    assert far.same_sequence and not far.same_timed_sequence
    assert far.end_gap < 1e-12  # the end points meet ...
    top, rms = far.path_deviation
    assert top == pytest.approx(1.0, abs=1e-3) and rms == pytest.approx(np.sqrt(0.5), abs=1e-2)
    same = TrialComparison("10 Hz fixed", "trial 2", ours, None, near)
    assert same.same_timed_sequence and same.path_deviation == (0.0, 0.0)
    assert TrialComparison("10 Hz fixed", "trial 3", None, None, near).path_deviation is None


def test_the_papers_counts_are_called_reproduced_only_where_a_mode_gets_them_exactly():
    from types import SimpleNamespace as Count

    from hmpc_cli.report.fig3 import Fig3Mode, _entry_text, _verdicts

    modes = [Fig3Mode("hmpc", "hmpc", None, None), Fig3Mode("reference", "ref", None, None)]
    counts = {"hmpc": {"10 Hz fixed": Count(successes=11, runs=11),
                       "20 Hz fixed": Count(successes=11, runs=11),
                       "100 Hz fixed": Count(successes=11, runs=11)},
              "reference": {"10 Hz fixed": Count(successes=11, runs=11),
                            "20 Hz fixed": Count(successes=10, runs=11)}}
    authors = {"100 Hz fixed": "4/11 (trial 3, trial 4)"}
    assert _verdicts(modes, counts, authors) == [
        "- 10 Hz fixed (the paper: 9/11): **not reproduced** by any mode (hmpc 11/11, "
        "reference 11/11).",
        "- 20 Hz fixed (the paper: 11/11): count reproduced by hmpc (hmpc 11/11, reference "
        "10/11).",
        # not in the paper: judged against the authors' data (it said only their count)
        "- 100 Hz fixed (not in the paper; the authors' data: 4/11): **not reproduced** by "
        "any mode (hmpc 11/11)."]
    assert _verdicts(modes, {"hmpc": {"100 Hz fixed": Count(successes=4, runs=11)},
                             "reference": {}}, authors) == [
        "- 100 Hz fixed (not in the paper; the authors' data: 4/11): count reproduced by "
        "hmpc (hmpc 4/11)."]
    assert _verdicts(modes, {"hmpc": {"50 Hz fixed": Count(successes=3, runs=11)},
                             "reference": {}}, authors) == [
        "- 50 Hz fixed: not in the paper (hmpc 3/11)."]
    partial = {"hmpc": {"10 Hz fixed": Count(successes=5, runs=5),
                        "20 Hz fixed": Count(successes=5, runs=5)},
               "reference": {"20 Hz fixed": Count(successes=10, runs=11)}}
    assert _verdicts(modes, partial, {}) == [  # a sweep stopped halfway is not judged
        "- 10 Hz fixed (the paper: 9/11): not judged: no mode holds its 11 runs yet (hmpc 5/5, "
        "6 runs missing).",
        "- 20 Hz fixed (the paper: 11/11): **not reproduced** by any mode (hmpc 5/5, 6 runs "
        "missing, reference 10/11)."]
    assert _entry_text([1.2, None, 1.4, 1.3], "authors") == "1.30 (authors: 3 of 4 entered)"
    assert _entry_text([1.2, 1.4], "hmpc") == "1.30" and _entry_text([None], "x") == "never"
