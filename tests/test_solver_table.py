"""The NLP back-end table: a new back-end is one entry; names are checked against it."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hmpc_cli.cli.app import app
from hmpc_cli.mpc import cache
from hmpc_cli.mpc.backends import rti_step_kept, rti_success
from hmpc_cli.mpc.solver import SolverSession, option_problems, plugin_options
from hmpc_cli.mpc.solver_table import (
    SOLVERS, Backend, SolverArgs, ipopt_options, register_backend, warm_options)
from hmpc_cli.run.scenario import ScenarioError, load_scenario, scenario_model

from conftest import bad_input

ROOT = Path(__file__).resolve().parents[1]
BALL = ROOT / "scenarios" / "ball.toml"
SHORT = ["sim.duration=0.3", "mpc.horizon=1.0"]
BUILT_IN = ["ipopt", "sqp_hpipm", "rti", "fatrop", "sqpmethod"]


@pytest.fixture
def table():
    """The table as it is; restored afterwards (entries a test registered are removed)."""
    saved = dict(SOLVERS)
    yield SOLVERS
    SOLVERS.clear()
    SOLVERS.update(saved)


@pytest.fixture
def twin(table):
    """``ipopt_twin``: IPOPT under another name, registered by one entry; its builds."""
    built: list[SolverArgs] = []

    def options(a: SolverArgs) -> dict:
        built.append(a)
        return ipopt_options(a)

    register_backend(Backend("ipopt_twin", "ipopt", options, summary="IPOPT again",
                             warm=warm_options, probe=True))
    return built


def test_the_built_in_entries_and_their_flags():
    assert list(SOLVERS)[:5] == BUILT_IN
    assert [n for n, b in SOLVERS.items() if b.stagewise] == ["sqp_hpipm", "rti", "fatrop"]
    assert [n for n, b in SOLVERS.items() if b.compilable] == ["ipopt"]
    assert [n for n, b in SOLVERS.items() if b.warm is not None] == ["ipopt", "rti"]
    assert SOLVERS["sqp_hpipm"].fallback == "ipopt" and SOLVERS["sqp_hpipm"].judge is rti_success
    assert SOLVERS["rti"].fallback is None and SOLVERS["rti"].judge is rti_step_kept
    assert SOLVERS["rti"].switching is None
    assert {n: b.plugin for n, b in SOLVERS.items()} == {
        "ipopt": "ipopt", "sqp_hpipm": "sqpmethod", "fatrop": "fatrop",
        "sqpmethod": "sqpmethod", "rti": "sqpmethod"}


def test_the_schema_lists_the_table(table):
    def enums() -> tuple[list, list]:
        props = scenario_model().model_json_schema()["$defs"]["MPCSettings"]["properties"]
        return props["solver"]["enum"], props["switching_solver"]["anyOf"][0]["enum"]

    assert enums() == (BUILT_IN, BUILT_IN)
    bundled = json.loads((ROOT / "scenarios" / "scenario.schema.json").read_text())
    assert bundled["$defs"]["MPCSettings"]["properties"]["solver"]["enum"] == BUILT_IN
    register_backend(Backend("ipopt_twin", "ipopt", ipopt_options))
    assert enums() == (BUILT_IN + ["ipopt_twin"], BUILT_IN + ["ipopt_twin"])


def test_an_unknown_solver_is_one_clear_line(tmp_path: Path):
    lines = bad_input(tmp_path, ["run", str(BALL), "--out", str(tmp_path / "out"),
                                 "--set", "mpc.solver=sqp_hpmip"])
    assert lines == ["error: --set mpc.solver=sqp_hpmip: mpc.solver: unknown NLP back-end "
                     "'sqp_hpmip' (did you mean 'sqp_hpipm'?); known: ipopt, sqp_hpipm, "
                     "rti, fatrop, sqpmethod"]
    with pytest.raises(ScenarioError) as err:
        load_scenario(BALL, ['mpc.switching_solver="knitro"'])
    assert err.value.lines == ['--set mpc.switching_solver="knitro": mpc.switching_solver: '
                               "unknown NLP back-end 'knitro'; known: ipopt, sqp_hpipm, "
                               "rti, fatrop, sqpmethod"]
    with pytest.raises(ValueError, match="unknown NLP back-end 'snopt'"):
        plugin_options("snopt", 5)


def test_a_registered_backend_runs_end_to_end_like_the_one_it_wraps(tmp_path: Path, twin):
    """The one entry is enough: the scenario validates, the set-up checks try its options,
    both NLPs are built through it, and the run is IPOPT's (same options)."""
    sc, _ = load_scenario(BALL, ['mpc.solver="ipopt_twin"', *SHORT])
    assert sc.mpc.solver_of(0) == sc.mpc.solver_of(3) == "ipopt_twin"
    summaries = {}
    for solver in ("ipopt", "ipopt_twin"):
        out = tmp_path / solver
        res = CliRunner().invoke(app, ["run", str(BALL), "--out", str(out), "-q",
                                       "--set", f"mpc.solver={solver}",
                                       *[a for s in SHORT for a in ("--set", s)]])
        assert res.exit_code == 0, (res.output, res.exception)
        summaries[solver] = json.loads((out / "summary.json").read_text())
    nlps = [a for a in twin if a.nlp is not None]  # the switching and the final NLP's
    assert len(nlps) == 2 and all(a.max_iter == sc.mpc.max_iter for a in nlps)
    ipopt, other = summaries["ipopt"], summaries["ipopt_twin"]
    assert other["solves"] > 0 and other["solver_failures"] == 0
    for key in ("solves", "contacts", "x_end", "final_error", "max_slack"):
        assert other[key] == ipopt[key], key
    # the set-up check solves a tiny NLP with its options (probe): a bad one is named
    assert option_problems("ipopt_twin", {}) == []
    assert "no_such_option" in " ".join(option_problems("ipopt_twin", {"no_such_option": 1}))


def test_the_session_dispatches_through_the_entry(twin):
    import casadi as ca
    import numpy as np

    x = ca.SX.sym("x")
    nlp = {"x": x, "p": ca.SX.sym("p", 0), "f": (x - 1) ** 2, "g": x}
    session = SolverSession("tiny", nlp, "ipopt_twin", max_iter=20,
                            extra={"hpipm": {"iter_max": 1}, "print_time": False})
    assert len(twin) == 1 and twin[0].nlp is nlp and twin[0].max_iter == 20
    assert twin[0].nlpsol == {"print_time": False} and twin[0].sections == {}
    assert session.warm is session.cold  # no WarmStart given
    res = session.run(np.zeros(1), np.zeros(0), -np.inf * np.ones(1), np.inf * np.ones(1),
                        np.array([2.0]), np.array([10.0]))
    assert res.stats.success and res.x[0] == pytest.approx(2.0, abs=1e-7)
    with pytest.raises(ValueError, match="cannot load a compiled NLP"):
        SolverSession("lib", "/nonexistent/nlp.so", "ipopt_twin", max_iter=5)


def test_stagewise_and_compilable_are_read_from_the_entry(table, monkeypatch):
    register_backend(Backend("stagewise_twin", "ipopt", ipopt_options, stagewise=True))
    with pytest.raises(ScenarioError, match='solver "stagewise_twin" needs stage-wise'):
        load_scenario(BALL, ['mpc.solver="stagewise_twin"'])
    sc, _ = load_scenario(BALL, ['mpc.solver="stagewise_twin"', 'mpc.input_hold="zoh"'])
    assert sc.mpc.solver == "stagewise_twin"
    monkeypatch.setenv(cache.ENV, "use")
    off = cache.lookup("0" * 64, "stagewise_twin").info
    assert off.cache == "disabled"
    assert off.reason == "solver 'stagewise_twin': compiled NLPs are for ipopt only"
    register_backend(replace(SOLVERS["stagewise_twin"], compilable=True))
    assert "compiled NLPs are for" not in cache.lookup("0" * 64, "stagewise_twin").info.reason


def test_an_entry_names_only_known_backends(table):
    with pytest.raises(ValueError, match="unknown back-end 'nope'"):
        register_backend(Backend("lonely", "ipopt", ipopt_options, fallback="nope"))
    assert "lonely" not in SOLVERS


def test_a_fatrop_section_merges_over_hmpcs_own_fatrop_options():
    """[mpc.solver_options.fatrop] adds fatrop's own options to hmpc's (print_level 0,
    mpc.max_iter, mpc.tol) instead of replacing them (which printed fatrop's iteration log
    on stdout and dropped the limits); another back-end never gets the section."""
    from hmpc_cli.mpc.solver import plugin_options

    opts = plugin_options("fatrop", 8, tol=1e-5, extra={"fatrop": {"mu_init": 0.1}})
    assert opts["fatrop"] == {"print_level": 0, "max_iter": 8, "tol": 1e-5, "mu_init": 0.1}
    assert "fatrop" not in plugin_options("ipopt", 8, extra={"fatrop": {"mu_init": 0.1}})


def test_sqpmethod_prints_no_status_line_per_solve():
    from hmpc_cli.mpc.solver import plugin_options

    assert plugin_options("sqpmethod", 8)["print_status"] is False
