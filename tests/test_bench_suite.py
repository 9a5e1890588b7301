"""The benchmark suite's machinery (benchmarks/suite.py) on a few problems of a short trial:
every configuration gets a row with finite numbers, failures are counted, the report
files are written, and a missing do-mpc is reported, not raised. No timing is asserted."""

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import suite
import suite_peers
import suite_report

from hmpc_cli.core.messages import SolveStats

#: a short horizon (15 nodes) and chain keep every NLP small
SHORT = ["mpc.horizon=0.5", "mpc.nodes_per_second=30", "mpc.max_switches=3"]
CONFIGS = {"authors", "ipopt_defaults", "hmpc_ipopt", "sqp_hpipm_rti1", "sqp_hpipm_rti3",
           "sqp_hpipm_conv", "fatrop", "rti"}


@pytest.fixture(scope="module")
def recorded():
    problems, packing = suite.record(1, SHORT)
    return problems, packing


@pytest.fixture(scope="module")
def measured(recorded):
    problems, packing = recorded
    chosen = suite.select(problems, 2)  # one of each NLP
    run = suite.measure(chosen, SHORT)
    run.packing = packing
    return chosen, run


def test_problems_are_recorded_from_both_nlps_and_spread(recorded):
    problems, packing = recorded
    kinds = [p.nlp for p in problems]
    assert {"final", "switching"} <= set(kinds)
    assert len(packing) == len(problems)  # one problem_data per solve
    chosen = suite.select(problems, 3)
    assert len(chosen) == 3 and {p.nlp for p in chosen} == {"final", "switching"}
    pos = [next(i for i, q in enumerate(problems) if q is p) for p in chosen]
    assert pos == sorted(pos)  # in recorded order
    assert all(a is b for a, b in zip(suite.select(problems, None), problems, strict=True))
    for p in chosen:  # the state the solve started from is the fixed first node
        assert p.x0.shape == (4,) and np.all(np.isfinite(p.x0))


def test_every_configuration_has_a_finite_row_per_nlp(measured, tmp_path):
    chosen, run = measured
    have_dompc = suite_peers.import_do_mpc() is not None
    table = suite_report.rows(run.stats)
    expected = CONFIGS | ({"do_mpc"} if have_dompc else set())
    n = {k: sum(p.nlp == k for p in chosen) for k in ("final", "switching")}
    n["all"] = len(chosen)
    for nlp in suite_report.NLPS:
        rows = {r.config: r for r in table if r.nlp == nlp}
        want = expected - ({"do_mpc"} if nlp != "final" else set())
        assert set(rows) == want, nlp
        for r in rows.values():
            assert r.solves == n[nlp]
            assert all(np.isfinite([r.median_ms, r.p95_ms, r.max_ms, r.mean_iter, r.vs_hmpc,
                                    r.authors_x]))
            assert 0 < r.median_ms <= r.p95_ms <= r.max_ms and r.mean_iter > 0
            assert 0 <= r.failures <= r.solves and 0 <= r.fallbacks <= r.solves
        assert rows["hmpc_ipopt"].vs_hmpc == pytest.approx(1.0)
        assert rows["hmpc_ipopt"].failures == 0
    best = suite_report.fastest(table)
    assert best in suite_report.HMPC
    desc = suite_report.machine(["suite.py"], (1.0, 1.0, 1.0), 1.0, [1], SHORT)
    text, paths = suite_report.write(run, desc, str(tmp_path))
    assert f"where the time goes: {best}" in text and "issue targets" in text
    with open(paths[1]) as f:
        assert len(list(csv.DictReader(f))) == len(table)
    page = Path(paths[0]).read_text()
    assert "## Machine" in page and "load average" in page and f"`{best}`" in page
    assert json.loads(Path(paths[2]).read_text())["cores"] >= 1
    if not have_dompc:
        assert any("do-mpc not installed" in note for note in run.notes)


def test_the_quick_command_end_to_end(recorded, tmp_path, monkeypatch, capsys):
    """``python benchmarks/suite.py --quick`` through its ``main`` (CI leaves the command
    itself to ``pytest -m campaign``): trial 1 recorded (the short NLPs' recording, 2
    problems), its report printed and written to results/bench/quick."""
    def record(trial, overrides):
        assert (trial, overrides) == (suite.QUICK_TRIALS[0], SHORT)
        return recorded

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(suite, "record", record)
    sets = [a for s in SHORT for a in ("--set", s)]
    assert suite.main(["--quick", "--problems", "2", "--no-do-mpc", *sets]) == 0
    out = tmp_path / "results" / "bench" / "quick"
    printed = capsys.readouterr().out
    assert "trial 1: " in printed and f"wrote {out.relative_to(tmp_path)}" in printed
    assert sorted(p.name for p in out.iterdir()) == ["backends.csv", "backends.md",
                                                     "machine.json"]
    with open(out / "backends.csv", newline="") as f:
        assert {r["config"] for r in csv.DictReader(f)} == CONFIGS


def test_failures_are_counted_and_ratios_are_of_medians():
    def st(ms, ok=True, fallback=False):
        return SolveStats("x", ok, 3, ms / 1e3, 0.0, 0.0, fallback=fallback)

    stats = {("hmpc_ipopt", "final"): [st(10), st(20), st(30)],
             ("authors", "final"): [st(400), st(500), st(600)],
             ("fatrop", "final"): [st(5), st(5, ok=False), st(5, fallback=True)]}
    rows = {r.config: r for r in suite_report.rows(stats) if r.nlp == "final"}
    assert rows["fatrop"].failures == 1 and rows["fatrop"].fallbacks == 1
    assert rows["fatrop"].vs_hmpc == pytest.approx(0.25)
    assert rows["hmpc_ipopt"].authors_x == pytest.approx(25.0)
    assert np.isnan(rows["fatrop"].dompc_x)


def test_step_11_targets_are_stated_for_the_default_and_the_fastest_configuration():
    def st(ms):
        return SolveStats("x", True, 3, ms / 1e3, 0.0, 0.0)

    stats = {("hmpc_ipopt", "final"): [st(8)] * 5, ("hmpc_ipopt", "switching"): [st(40)] * 3,
             ("rti", "final"): [st(2)] * 5, ("rti", "switching"): [st(9)] * 3,
             ("ipopt_defaults", "final"): [st(16)] * 5,
             ("ipopt_defaults", "switching"): [st(60)] * 3,
             ("do_mpc", "final"): [st(42)] * 5}  # all solves: the final NLP's median
    table = suite_report.rows(stats)
    sections = dict(suite_report.target_sections(table, suite_report.fastest(table)))
    assert list(sections) == ["hmpc_ipopt, the default configuration", "rti, the fastest back-end"]
    rti = sections["rti, the fastest back-end"]
    assert "switching solves median 9.00 ms (target <= 15 ms): met" in rti
    assert "switching solves p95 9.00 ms (target <= 30 ms): met" in rti
    assert "all solves median 2.00 ms (target <= 3 ms): met" in rti
    assert "8.0x faster than IPOPT defaults, all solves (target >= 5x): met" in rti
    assert "21.0x faster than do-mpc, final NLP (target >= 20x): met" in rti
    ipopt = sections["hmpc_ipopt, the default configuration"]
    assert "switching solves median 40.00 ms (target <= 15 ms): NOT met" in ipopt
    assert "5.2x faster than do-mpc, final NLP (target >= 20x): NOT met" in ipopt


def test_the_profile_parts_add_up_to_the_call():
    split = {"QP": 0.002, "nlp_fg": 0.0005, "nlp_jac_fg": 0.001, "linesearch": 0.0007,
             "total": 0.004, "casadi_call": 0.0045, "cpu_casadi_call": 0.003,
             "call (hmpc + CasADi)": 0.005}
    fell_back = {**split, "call (hmpc + CasADi)": 1.0}
    stats = [SolveStats("x", True, 2, 0.005, 0.0, 0.0),
             SolveStats("x", True, 9, 1.0, 0.0, 0.0, fallback=True)]
    prof = {k: (md, mn, sh) for k, md, mn, sh in
            suite_report.profile([split, fell_back], stats, [0.001])}
    parts = [prof[k] for k in suite_report.PARTS if k in prof]
    assert sum(mn for _, mn, _ in parts) == pytest.approx(prof["whole solve call"][1])
    assert prof["whole solve call"][1] == pytest.approx(5.0)  # the fallback is left out
    assert prof["QP solve (HPIPM via CasADi)"][1] == pytest.approx(2.0)
    assert prof["line search (net of its nlp_fg)"][1] == pytest.approx(0.2)
    assert prof["hmpc's Python around the call"][1] == pytest.approx(0.5)
    assert prof["CasADi call, CPU (process) time"][1] == pytest.approx(3.0)
    assert prof["one QP (QP time / SQP iterations)"][1] == pytest.approx(1.0)


def test_missing_do_mpc_is_reported_not_raised(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "do_mpc", None)  # `import do_mpc` raises ImportError
    assert suite_peers.import_do_mpc() is None
    run = suite.SuiteRun()
    assert suite.dompc_config(None, run) is None
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "do-mpc not installed" in out[0] and ".[bench]" in out[0]
    assert run.notes == ["do-mpc not installed (pip install -e '.[bench]'): its row is left out"]


def test_every_hmpc_back_end_gets_a_profile_or_says_why_not(measured):
    """The report profiles its fastest back-end, which the machine's load picks: each of
    them must have a profile, or a line saying its solves all fell back to IPOPT."""
    _, run = measured
    for label in suite_report.HMPC:
        text = "\n".join(suite_report.profile_lines(run, label))
        assert f"where the time goes: {label}" in text, label
        for nlp in ("final", "switching"):
            stats = run.stats.get((label, nlp), [])
            if stats and all(s.fallback for s in stats):
                assert (f"{label}, {nlp} NLP: every one of its {len(stats)} solves fell back "
                        "to IPOPT") in text
