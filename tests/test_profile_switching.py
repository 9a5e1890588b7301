"""The switching-solve profile (benchmarks/profile_switching.py) on two recorded problems of
a short chain: the problems are recorded as the closed loop solved them, every variant
re-solves them, and the report has its fixed structure. No timing is asserted."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import profile_switching as ps
import suite_report

from hmpc_cli.mpc.chain.problem_data import problem_data

#: a short horizon (15 nodes) and chain keep every NLP small
SHORT = ["mpc.horizon=0.5", "mpc.nodes_per_second=30", "mpc.max_switches=3"]


@pytest.fixture(scope="module")
def inputs():
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HMPC_BUILD_CACHE", "off")
        problems, info = ps.record("trial 1", [*SHORT, *ps.DISTURBED, "disturbance.trial=1"])
        switching = [p for p in problems if p.nlp == "switching"][:2]
        final = [p for p in problems if p.nlp == "final"][:2]
        sysm, s = ps.settings_of(SHORT)
        nlps = {"switching": ps.FixedModeNLP(sysm, s),
                "final": ps.FixedModeNLP(sysm, s, switches=0)}
        kkt = {k: ps.kkt_size(nlp, [p for p in problems if p.nlp == k])
               for k, nlp in nlps.items()}
        prof = ps.replay(switching, nlps["switching"])
        prof.final = ps.replay_final(final, nlps["final"])
        loops = [ps.LoopVariant(ps.CLOSED_LOOP[0][0], [p.recorded for p in switching], [info],
                                ps._size_of(sysm, s)),
                 ps.closed_loop('integrator = "euler"', [*SHORT, 'mpc.integrator="euler"'],
                                (1,))]
    machine = suite_report.machine(["profile_switching.py"], (1.0, 1.0, 1.0), 1.0, [], [])
    return ps.Inputs(prof, [info], kkt, loops, ps.Compiled(0, note="not asked for"),
                     machine), nlps


def test_recorded_problems_are_the_closed_loops(inputs):
    x, nlps = inputs
    probs = x.prof.problems
    assert len(probs) == 2 and all(p.nlp == "switching" and p.ns.guards for p in probs)
    nlp = nlps["switching"]
    for p in probs:  # the recorded parameters and bounds are the problem's own
        for got, want in zip(problem_data(nlp.shape, p.ns, p.lay, p.x0), p.args[1:6],
                             strict=True):
            np.testing.assert_array_equal(got, want)
        assert ps.bucket_of(p) in [label for _, label in ps.BUCKETS]
        assert p.context in ("cold (new plan)", "after impact", "shifted")
    assert probs[0].context == "cold (new plan)" and probs[0].args[6] is None


def test_every_variant_re_solves_and_the_timers_are_read(inputs):
    x, _ = inputs
    prof = x.prof
    assert set(prof.meas) == {v.name for v in ps.VARIANTS}
    for v in ps.VARIANTS:
        got = prof.meas[v.name]
        # problem 0 (cold in the closed loop): every variant but the unshifted previous
        # solution (none); problem 1: every variant re-solving every problem
        assert len(got) == 2, v.name
        assert (got[0] is None) == (v.what is ps.unshifted), v.name
        assert (got[1] is None) == (v.every > 1), v.name
        m = got[0] or got[1]
        assert m.iterations >= 0 and m.total > 0 and m.wall >= m.total
        assert set(m.evals) == set(ps.EVALS) and m.rest >= 0
    assert prof.meas[ps.BASELINE][0].success
    assert prof.timers and all("OverallAlgorithm" in t for t in prof.timers)
    assert len(prof.final) == 2 and all(m.success for m in prof.final)
    sw, fi = x.kkt["switching"], x.kkt["final"]
    assert sw["vars"] > fi["vars"] and sw["rows"] > fi["rows"]
    assert sw["groups"]["dynamics"]["rows"] == sw["eq"]


def test_report_structure(inputs):
    x, _ = inputs
    text = ps.report(x)
    heads = re.findall(r"^#+ (.+)$", text, flags=re.M)
    assert heads == [
        "Profile of the switching MPC solve (ball, Figure 3 trials)", "Machine and load",
        "Recorded problems", "1. Per solve: iterations and where IPOPT's time goes",
        "IPOPT's own timing statistics (switching problems, summed over the solves)",
        "Evaluations compiled (short chain)", "2. KKT size per NLP",
        "3. Row groups relaxed (same problems)", "4. Warm start",
        "5. IPOPT options (same NLP, same warm start)", "6. Structural settings in closed loop",
        "7. Iterations vs the time to the next planned switch", "What the profile says"]
    assert x.machine["cpu"] in text and "cores" in text and "machine dependent" in text
    for v in ps.VARIANTS:
        if v.section != "stats":
            assert f"| {v.name} |" in text, v.name
    for _, label in ps.BUCKETS:
        assert f"| {label} |" in text
    for name in ps.GROUPS:
        assert f"| {name} |" in text
    levers = re.findall(r"^\d+\. \*\*", text, flags=re.M)
    assert len(levers) == 10
    # every table row has as many cells as its header
    for block in re.findall(r"((?:^\|.*\|\n)+)", text, flags=re.M):
        lines = block.strip().splitlines()
        assert len({ln.count("|") for ln in lines}) == 1, lines[0]
