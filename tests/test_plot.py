"""``hmpc plot fig3``: Figure 3 drawn from short recorded runs; deterministic files, bad input."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from conftest import BALL, cli_env, hmpc_command
from figcheck import assert_legible
from hmpc_cli.cli.plot import plot_command

FAST = ["--set", "sim.duration=0.6", "--set", "planner.iterations=3", "-q"]
RUNS = {"nom": [], "t1": ["--set", "disturbance.kind=\"paper_fig3\"", "--set",
                          "disturbance.trial=1"],
        "t2": ["--set", "disturbance.kind=\"paper_fig3\"", "--set", "disturbance.trial=2"]}
COLUMNS = ["run_id", "controller", "disturbance", "seed", "success", "final_error", "contacts",
           "solver_failures", "log"]
# (controller, disturbance, success, run directory): panel A holds one failed run.
ROWS = [("A", "trial 1", True, "t1"), ("A", "nominal", True, "nom"), ("A", "trial 2", False, "t2"),
        ("B", "nominal", True, "nom"), ("B", "trial 1", True, "t1")]
# A stand-alone app with only the plot command, run in a fresh process.
APP = ("import sys, typer; from hmpc_cli.cli.plot import plot_command; app = typer.Typer(); "
       "app.callback()(lambda: None); app.command('plot')(plot_command); "
       "sys.argv[0] = 'hmpc'; app()")


def make_app() -> typer.Typer:
    app = typer.Typer()
    app.callback()(lambda: None)  # keep "plot" a subcommand
    app.command("plot")(plot_command)
    return app


def write_table(path: Path, rows, runs_rel: dict[str, str], columns=COLUMNS) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        for i, (ctrl, dist, ok, run) in enumerate(rows):
            full = {"run_id": i, "controller": ctrl, "disturbance": dist, "seed": 0,
                    "success": ok, "final_error": 0.1, "contacts": 1, "solver_failures": 0,
                    "log": runs_rel[run]}
            w.writerow([full[c] for c in columns])
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Three short recorded ball runs (nominal, trials 1 and 2), made in parallel."""
    base = tmp_path_factory.mktemp("plot_runs")
    procs = {k: subprocess.Popen([*hmpc_command(), "run", str(BALL), "--out", str(base / k),
                                  *FAST, *extra], cwd=base, env=cli_env(),
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k, extra in RUNS.items()}
    for k, p in procs.items():
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, f"run {k} failed: {err}"
    return {k: base / k / "run.mcap" for k in RUNS}


@pytest.fixture
def table(runs, tmp_path) -> Path:
    """results.csv with runs in two panels, logs relative to the table's directory."""
    sweep = tmp_path / "sweep"
    rel = {}
    for k, log in runs.items():
        (sweep / "runs" / k).mkdir(parents=True)
        (sweep / "runs" / k / "run.mcap").write_bytes(log.read_bytes())
        rel[k] = f"runs/{k}/run.mcap"
    return write_table(sweep / "results.csv", ROWS, rel)


def plot_proc(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", APP, "plot", *args], cwd=cwd, env=cli_env(),
                          capture_output=True, text=True, timeout=120)


def read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB")).astype(int)


def has_color(img: np.ndarray, hex_color: str, tol: int = 12) -> bool:
    rgb = np.array([int(hex_color[i:i + 2], 16) for i in (1, 3, 5)])
    return bool((np.abs(img - rgb).max(axis=2) <= tol).any())


@pytest.mark.slow
def test_fig3_writes_figures_and_counts_deterministically(table, tmp_path):
    first = plot_proc(["fig3", str(table)], tmp_path)
    assert first.returncode == 0, first.stderr
    sweep = table.parent
    for fmt in ("pdf", "svg", "png"):
        assert (sweep / f"fig3.{fmt}").stat().st_size > 5000
    assert (sweep / "fig3.pdf").read_bytes().startswith(b"%PDF")
    assert b"<svg" in (sweep / "fig3.svg").read_bytes()[:2000]
    with open(sweep / "fig3_counts.csv", newline="") as f:
        counts = list(csv.reader(f))
    assert counts == [["panel", "runs", "successes", "failed"], ["A", "3", "2", "trial 2"],
                      ["B", "2", "2", ""]]
    assert "A" in first.stdout and "paper" not in first.stdout  # no reference for A/B
    # Same input, another process, another directory: the same bytes in every format.
    again = plot_proc(["fig3", str(table), "--out", str(tmp_path / "again")], tmp_path)
    assert again.returncode == 0, again.stderr
    for name in ("fig3.pdf", "fig3.svg", "fig3.png", "fig3_counts.csv"):
        assert (tmp_path / "again" / name).read_bytes() == (sweep / name).read_bytes(), name


def test_png_size_and_marks(table, tmp_path):
    from hmpc_cli.figures.fig3 import FAIL_COLOR, NOMINAL_COLOR, START_COLOR, fig3

    fig3(table, tmp_path / "all", formats="png")
    img = read_png(tmp_path / "all" / "fig3.png")
    assert img.shape == (630, 1050, 3)  # one column: 3.5 x 2.1 in at 300 dpi
    assert (img < 50).all(axis=2).mean() > 0.002  # black guards, text, end points
    for color in (NOMINAL_COLOR, START_COLOR, FAIL_COLOR):
        assert has_color(img, color), color
    fig3(table, tmp_path / "b", formats="png", panels=["B"], width=3.5, height=2.0)
    img_b = read_png(tmp_path / "b" / "fig3.png")
    assert img_b.shape == (600, 1050, 3)
    assert not has_color(img_b, FAIL_COLOR)  # panel B has no failed run: no red cross
    fig3(table, tmp_path / "wide", formats="png", width=7.16, height=2.5)  # --width overrides
    assert read_png(tmp_path / "wide" / "fig3.png").shape == (750, 2148, 3)


PAPER_ROWS = [(c, d, ok, run) for c in ("10 Hz fixed", "20 Hz fixed", "10 Hz replan")
              for d, ok, run in (("nominal", True, "nom"), ("trial 1", True, "t1"),
                                 ("trial 2", c != "10 Hz fixed", "t2"))]


@pytest.mark.parametrize("width,height", [(None, None), (7.16, 2.5)])
def test_fig3_is_legible_at_its_size(runs, tmp_path, width, height):
    """Three panels with the paper's titles at one column (the default) and at text width:
    the figure is the size asked for, STIX, text >= 7 pt, no two texts overlap."""
    from hmpc_cli.figures import fig3 as f3
    from hmpc_cli.figures.common import COLUMN_WIDTH_IN, figure_style
    from hmpc_cli.analysis.tables import read_table

    table = write_table(tmp_path / "results.csv", PAPER_ROWS, {k: str(v) for k, v in runs.items()})
    rows = read_table(table, ["controller", "disturbance", "success", "log"])
    loaded = f3._load_runs(table, f3._group(rows, "controller", None, table), "disturbance",
                           "nominal", {})
    assert len(loaded) == 3
    width, height = width or f3.fig3.__kwdefaults__["width"], height or f3.HEIGHT_IN
    assert f3.fig3.__kwdefaults__["width"] == COLUMN_WIDTH_IN == 3.5
    with figure_style():
        import matplotlib as mpl

        assert mpl.rcParams["mathtext.fontset"] == "stix"
        fig = f3._figure(loaded, width, height, None)
        assert_legible(fig, width, height)
        legend = fig.legends[0]
        box = legend.get_window_extent()
        assert all(box.y1 <= ax.get_window_extent().y0 for ax in fig.axes)  # below the panels
        ratios = {round(ax.get_position().width * width / (ax.get_position().height * height), 2)
                  for ax in fig.axes}
        assert len(ratios) == 1  # equal panels


def test_panel_order_reference_counts_and_sweep_dir(runs, tmp_path):
    rel = {k: str(v) for k, v in runs.items()}  # absolute log paths are fine too
    rows = [("10 Hz replan", "nominal", True, "nom"), ("10 Hz fixed", "trial 10", False, "t1"),
            ("10 Hz fixed", "nominal", True, "nom"), ("10 Hz fixed", "trial 2", False, "t2")]
    table = write_table(tmp_path / "s" / "results.csv", rows, rel)
    app, env = make_app(), {"COLUMNS": "200", "NO_COLOR": "1"}
    # A sweep directory works as the table; the paper's panels keep the paper's order.
    res = CliRunner().invoke(app, ["plot", "fig3", str(tmp_path / "s"), "--formats", "png"],
                             env=env)
    assert res.exit_code == 0, res.output
    assert "9/11" in res.stdout and "11/11" in res.stdout  # the paper's counts beside ours
    assert sorted(p.name for p in table.parent.iterdir()) == [
        "fig3.png", "fig3_counts.csv", "results.csv"]
    lines = (table.parent / "fig3_counts.csv").read_text().splitlines()
    assert lines[1:] == ["10 Hz fixed,3,1,trial 2;trial 10", "10 Hz replan,1,1,"]
    res = CliRunner().invoke(app, ["plot", "fig3", str(table), "--formats", "png", "--panels",
                                   "10 Hz replan,10 Hz fixed"], env=env)
    assert res.exit_code == 0, res.output
    lines = (table.parent / "fig3_counts.csv").read_text().splitlines()
    assert [ln.split(",")[0] for ln in lines[1:]] == ["10 Hz replan", "10 Hz fixed"]


def test_bounces_touch_the_guard(runs):
    from hmpc_cli.analysis.tables import load_trace

    tr = load_trace(runs["nom"])
    r = tr.system["radius"]
    assert tr.xy.shape[1] == 2 and np.all(np.diff(tr.t) >= 0)
    assert tr.xy[:, 1].min() == pytest.approx(r, abs=1e-6)  # event points spliced in
    assert tr.xy[0].tolist() == [1.0, 1.0]


def test_rc_params_do_not_leak(table, tmp_path):
    import matplotlib as mpl

    from hmpc_cli.figures.fig3 import fig3

    before = {k: v for k, v in mpl.rcParams.items() if k != "backend"}
    fig3(table, tmp_path / "o", formats="svg")
    after = {k: v for k, v in mpl.rcParams.items() if k != "backend"}
    assert before == after


def test_plot_module_is_light_and_uses_no_pyplot(table, tmp_path):
    code = ("import sys; import hmpc_cli.cli.plot; assert 'matplotlib' not in sys.modules; "
            "from hmpc_cli.figures.fig3 import fig3; "
            f"fig3({str(table)!r}, {str(tmp_path / 'o')!r}, 'png'); "
            "assert 'matplotlib.pyplot' not in sys.modules; print('ok')")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr


def bad_cases(table: Path, tmp: Path) -> dict[str, list[str]]:
    """Name -> plot arguments that must be refused."""
    no_cols = tmp / "nocols.csv"
    no_cols.write_text("run_id,controller,success\n0,A,True\n")
    text = table.read_text()
    missing_log = tmp / "missing_log" / "results.csv"
    missing_log.parent.mkdir()
    missing_log.write_text(text.replace("runs/t2/run.mcap", "runs/t9/run.mcap"))
    bad_bool = tmp / "bad_bool" / "results.csv"
    bad_bool.parent.mkdir()
    bad_bool.write_text(text.replace("False", "maybe"))
    not_mcap = tmp / "not_mcap" / "results.csv"
    (not_mcap.parent / "runs").mkdir(parents=True)
    (not_mcap.parent / "runs" / "x.mcap").write_text("hello")
    not_mcap.write_text(text.replace("runs/t2/run.mcap", "runs/x.mcap"))
    header_only = tmp / "empty.csv"
    header_only.write_text(",".join(COLUMNS) + "\n")
    return {
        "missing table": ["fig3", str(tmp / "nope.csv")],
        "missing columns": ["fig3", str(no_cols)],
        "missing log": ["fig3", str(missing_log)],
        "not an mcap log": ["fig3", str(not_mcap)],
        "bad success": ["fig3", str(bad_bool)],
        "no rows": ["fig3", str(header_only)],
        "unknown figure": ["fig9", str(table)],
        "unknown panel": ["fig3", str(table), "--panels", "A,Z"],
        "unknown format": ["fig3", str(table), "--formats", "pdf,jpg"],
        "bad view": ["fig3", str(table), "--view", "0,1,2"],
        "view not finite": ["fig3", str(table), "--view", "0,nan,0,1"],
        "view empty": ["fig3", str(table), "--view", "1,0,0,1"],
        "another figure's option": ["fig2", str(table), "--view", "0,1,0,1"],
        "fig4's option for fig3": ["fig3", str(table), "--every", "0.2"],
        "unknown trace axis": ["fig3", str(table), "--trace-axis", "wind"],
        "unknown nominal": ["fig3", str(table), "--nominal", "bogus"],
    }


def test_bad_input_exits_2_and_writes_nothing(table, tmp_path):
    app = make_app()
    for name, args in bad_cases(table, tmp_path).items():
        out = tmp_path / f"out_{name.replace(' ', '_')}"
        before = sorted(p.name for p in table.parent.iterdir())
        res = CliRunner().invoke(app, ["plot", *args, "--out", str(out)])
        assert res.exit_code == 2, f"{name}: {res.output}"
        err = res.stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: "), f"{name}: {res.stderr!r}"
        assert not out.exists(), name
        assert sorted(p.name for p in table.parent.iterdir()) == before, name
    res = CliRunner().invoke(app, ["plot", "robustness", str(table), "--no-gif"])
    assert res.stderr == ("error: --no-gif is fig4's option, not robustness's (it would be "
                          "ignored): leave it out\n")
    # Without --out the table's own directory stays untouched as well.
    res = CliRunner().invoke(app, ["plot", "fig9", str(table)])
    assert res.exit_code == 2 and not (table.parent / "fig3.png").exists()


@pytest.mark.parametrize("layout,size", [(None, (2.0, 1.5)), ("constrained", (2.0, 1.5)),
                                         (None, (2.26, 1.5))])
def test_save_gif_is_matplotlibs_pillow_animation(tmp_path, layout, size, monkeypatch):
    """save_gif writes the bytes Animation.save writes with PillowWriter (axes and title
    changing per frame, with and without a layout engine; a width whose pixels round up),
    at the resolution asked; a stop inside a frame or a failed write leaves no file."""
    from matplotlib.animation import FuncAnimation, PillowWriter
    from PIL import Image

    from hmpc_cli.figures.common import figure_style, save_gif

    def make():
        fig, ax = plt.subplots(figsize=size, layout=layout)

        def draw(k: int) -> None:
            ax.clear()
            ax.plot([0, 1], [0, k])
            ax.set_title(f"t = {k / 10:.2f} s")
        return fig, draw

    with figure_style():
        import matplotlib.pyplot as plt

        dpi = 80 if size[0] == 2.0 else 150  # 2.26 in x 150 dpi = 338.99999999999994
        fig, draw = make()
        FuncAnimation(fig, draw, frames=4).save(tmp_path / "ref.gif", writer=PillowWriter(fps=10),
                                                dpi=dpi)
        plt.close(fig)
        fig, draw = make()
        save_gif(fig, draw, range(4), tmp_path / "ours.gif", 10, dpi=dpi)
        assert (tmp_path / "ours.gif").read_bytes() == (tmp_path / "ref.gif").read_bytes()
        with Image.open(tmp_path / "ours.gif") as im:
            assert im.size == ((160, 120) if dpi == 80 else (339, 225))
            assert im.n_frames == 4 and im.info["duration"] == 100

        def stopped(k: int) -> None:
            if k == 2:
                raise KeyboardInterrupt
            draw(k)

        with pytest.raises(KeyboardInterrupt):
            save_gif(fig, stopped, range(4), tmp_path / "stopped.gif", 10)
        with pytest.raises(ValueError, match="at least one frame"):
            save_gif(fig, draw, [], tmp_path / "empty.gif", 10)

        def half_written(self, fp, *args, **kwargs):  # a disk that fills up mid-file
            Path(fp).write_bytes(b"GIF89a")
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(Image.Image, "save", half_written)
        with pytest.raises(OSError, match="No space"):
            save_gif(fig, draw, range(2), tmp_path / "full.gif", 10)
        plt.close(fig)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ours.gif", "ref.gif"]


def test_a_missing_column_the_table_has_as_a_fixed_setting_is_suggested(tmp_path):
    """A sweep's fixed settings are its set.<key> columns: `hmpc plot robustness` on a
    Figure 3 table said only 'missing column(s) mpc.rate_hz, replanning.policy'."""
    from hmpc_cli.analysis.tables import FigureInputError, read_table

    table = tmp_path / "results.csv"
    table.write_text("run_id,set.mpc.rate_hz,set.replanning.policy,succes,log\n"
                     "a,10,once,True,runs/a/run.mcap\n")
    with pytest.raises(FigureInputError) as info:
        read_table(table, ["mpc.rate_hz", "replanning.policy", "success", "wind"])
    assert str(info.value) == (
        f"{table}: missing column(s) mpc.rate_hz (did you mean 'set.mpc.rate_hz'?), "
        "replanning.policy (did you mean 'set.replanning.policy'?), success (did you mean "
        "'succes'?), wind (has: run_id, set.mpc.rate_hz, set.replanning.policy, succes, log)")


def test_a_table_with_a_run_twice_is_refused_by_line(tmp_path):
    """A results.csv edited by hand with a run's row twice was counted twice (17 runs of a
    16-run sweep on the page and in plot robustness)."""
    from hmpc_cli.analysis.tables import FigureInputError, read_table

    table = tmp_path / "results.csv"
    table.write_text("run_id,success\na1,true\nb2,false\na1,false\n")
    with pytest.raises(FigureInputError) as info:
        read_table(table, ["success"])
    assert str(info.value) == (f"{table}:4: run_id 'a1' again (line 2): a sweep's table holds "
                               "each run once; keep one of the two rows")


def test_a_figures_png_is_the_same_whatever_other_formats_are_saved_with_it(tmp_path):
    """Each format is drawn from the same layout: fig3's PNG saved after its PDF (the
    default formats) differed from the PNG saved alone in about 21,000 pixels (a draw
    moves fixed-aspect axes under the constrained layout)."""
    from conftest import REPO

    table = REPO / "results" / "sweeps" / "fig3"
    made = {}
    for formats in ("png", "pdf,svg,png"):
        out = tmp_path / formats.replace(",", "_")
        proc = subprocess.run([*hmpc_command(), "plot", "fig3", str(table), "--formats",
                               formats, "--out", str(out), "-q"], env=cli_env(),
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr
        made[formats] = (out / "fig3.png").read_bytes()
    assert made["png"] == made["pdf,svg,png"]


@pytest.mark.parametrize("figure, table, taken", [
    ("robustness", "robustness", "robustness.png"),
    ("robustness", "robustness", "robustness_table.csv"),
    ("fig3", "fig3", "fig3_counts.csv"),
    ("fig3", "fig3", "fig3.png")])
def test_a_directory_where_a_figure_file_goes_is_refused_before_any_file(tmp_path, figure,
                                                                        table, taken):
    """A directory named as one of the outputs: exit 2 naming it, no file written (the
    PDF and SVG were written before the PNG failed, or the figure before its table)."""
    from conftest import REPO

    out = tmp_path / "out"
    (out / taken).mkdir(parents=True)
    proc = subprocess.run([*hmpc_command(), "plot", figure,
                           str(REPO / "results" / "sweeps" / table), "--out", str(out)],
                          env=cli_env(), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"error: {out / taken}: is a directory, where this command writes a file: remove "
        "it or choose another output directory"]
    assert [p.name for p in out.iterdir()] == [taken]


def test_a_table_whose_logs_are_all_missing_is_one_short_error(tmp_path):
    """Every log missing: one line naming the first three and the count (it was one line of
    every row, each naming its place twice: 5.8 kB for the Figure 3 table)."""
    from conftest import REPO

    d = tmp_path / "nolog"
    d.mkdir()
    (d / "results.csv").write_bytes((REPO / "results/sweeps/fig3/results.csv").read_bytes())
    with open(d / "results.csv") as f:
        ids = [r["run_id"] for r in csv.DictReader(f)]
    proc = subprocess.run([*hmpc_command(), "plot", "fig3", str(d)], env=cli_env(),
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 2
    table = d / "results.csv"
    assert proc.stderr.splitlines() == [
        f"error: {table}: no readable run log: " + "; ".join(
            f"{table}:{i + 2}: skipped: log {d}/runs/{ids[i]}/run.mcap does not exist"
            for i in range(3)) + f"; ... ({len(ids)} rows in all)"]


def test_fig4_names_its_every_option_and_keeps_the_gif_with_the_figure(tmp_path):
    from conftest import REPO

    walk = REPO / "results" / "biped_stairs" / "report"
    zero = subprocess.run([*hmpc_command(), "plot", "fig4", str(walk), "--every=0", "--out",
                           str(tmp_path / "z")], env=cli_env(), capture_output=True,
                          text=True, timeout=600)
    assert zero.returncode == 2 and zero.stderr.splitlines() == [
        "error: --every: the time between snapshots must be > 0 s (got 0)"]
    out = tmp_path / "g"
    (out / "walk.gif").mkdir(parents=True)  # drawn after fig4.pdf and fig4.png
    gif = subprocess.run([*hmpc_command(), "plot", "fig4", str(walk), "--out", str(out)],
                         env=cli_env(), capture_output=True, text=True, timeout=600)
    assert gif.returncode == 2 and gif.stderr.splitlines() == [
        f"error: {out / 'walk.gif'}: is a directory, where this command writes a file: "
        "remove it or choose another output directory"]
    assert [p.name for p in out.iterdir()] == ["walk.gif"]


def test_save_figure_takes_any_iterable_of_formats(tmp_path):
    """A generator of formats was used up by the output check: nothing was written."""
    from matplotlib.figure import Figure

    from hmpc_cli.figures.common import save_figure

    fig = Figure()
    fig.subplots().plot([0, 1], [1, 0])
    paths = save_figure(fig, tmp_path, "x", (f for f in ["png", "pdf"]))
    assert [p.name for p in paths] == ["x.png", "x.pdf"] and all(p.is_file() for p in paths)
