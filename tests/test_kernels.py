"""Stage kernels compiled to C (hmpc_cli/mpc/kernels.py): the chain NLP's cost, rows and
derivatives evaluate their stages in C once a run has compiled them, with the numbers of
the SX kernels bit for bit; the cache off, nothing is compiled; a damaged library is never
loaded."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hmpc_cli.core import cbuild
from hmpc_cli.core.registry import build_system
from hmpc_cli.mpc import cache, kernels
from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule
from hmpc_cli.mpc.chain.nlp import FixedModeNLP
from hmpc_cli.run.scenario import load_scenario
from conftest import nlp_function_calls

pytestmark = pytest.mark.skipif(cbuild.compiler() is None, reason="no C compiler")

REPO = Path(__file__).resolve().parents[1]
TINY = ["mpc.horizon=0.2", "mpc.nodes_per_second=20", "mpc.max_switches=1"]


@pytest.fixture
def tiny(monkeypatch, tmp_path):
    """The ball, the tiny chain's settings, and an empty private cache in the default mode."""
    folder = tmp_path / "cache"
    folder.mkdir(mode=0o700)
    monkeypatch.setenv("HMPC_CACHE_DIR", str(folder))
    monkeypatch.setenv(cache.ENV, "use")
    monkeypatch.setattr(kernels, "_WAIT", False)  # a single run's process (not a sweep's)
    monkeypatch.setattr(kernels, "NICE", ())  # compiles not starved by a loaded machine
    sc, _ = load_scenario(REPO / "scenarios" / "ball.toml", TINY)
    return build_system(sc.system), sc.mpc, folder


def _libraries(folder: Path) -> list[Path]:
    return sorted(folder.glob("kernel-*.so"))


#: the kernels of the tiny chain's switching NLP: per kind of stage, its rows, cost (a
#: link's), their Jacobian and gradient, and its Lagrangian's Hessian
KERNELS = {f"{kind}_{what}" for kind in ("link_foh", "link_held", "last_node")
           for what in ("rows", "cost", "jac", "grad", "hess")} - {"last_node_cost",
                                                                 "last_node_grad"}


def _stage_classes(nlp: FixedModeNLP) -> set[str]:
    """The kinds of function IPOPT's maps call: its NLP's (f, g) and the derivatives given."""
    functions = [nlp.session.cold.oracle(), *(nlp.session.options[k] for k in
                                               ("grad_f", "jac_g", "hess_lag"))]
    stages = {f.name(): f.class_name() for fn in functions for f in fn.find_functions()
              if f.class_name() != "Map"}
    assert set(stages) == KERNELS
    return set(stages.values())


def _solves(nlp: FixedModeNLP, ball) -> list:
    ns = NodeSchedule((0,), (), (nlp.N,))
    data = nlp.problem_data(ns, ChainLayout.build(ns, nlp.L), ball.x0)
    cold = nlp.optimize(np.zeros(nlp.nx_var), *data)
    return [cold, nlp.optimize(cold.x, *data, cold.lam_x, cold.lam_g)]


def test_a_second_build_evaluates_the_nlp_in_c_with_the_same_numbers(tiny):
    system, settings, folder = tiny
    first = FixedModeNLP(system, settings)  # compiles its kernels beside it
    assert kernels.wait()
    assert len(_libraries(folder)) == len(KERNELS) == 13
    second = FixedModeNLP(system, settings)
    assert _stage_classes(second) == {"External"}  # the libraries are called
    assert _stage_classes(first) == {"SXFunction"}
    clause = "; cost, rows and derivatives assembled stage by stage: stage kernels in "
    assert first.build_info.reason.endswith(f"{clause}SX (13 of 13)")
    assert second.build_info.reason.endswith(f"{clause}C (13)")
    rng = np.random.default_rng(0)
    for _ in range(5):
        for name, args in nlp_function_calls(rng, second.nx_var, second.np, second.ng):
            a, b = (nlp.session.cold.get_function(name).call(args) for nlp in (first, second))
            for out_a, out_b in zip(a, b, strict=True):
                np.testing.assert_array_equal(out_a.full(), out_b.full())
    for a, b in zip(_solves(first, system), _solves(second, system), strict=True):
        assert a.stats.success and a.stats.iterations == b.stats.iterations
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.lam_g, b.lam_g)


def test_the_cache_off_compiles_no_kernel(tiny, monkeypatch):
    system, settings, folder = tiny
    monkeypatch.setenv(cache.ENV, "off")
    FixedModeNLP(system, settings)
    assert kernels.wait()
    assert _libraries(folder) == []


def test_damaged_kernel_libraries_are_not_loaded_but_compiled_again(tiny):
    system, settings, folder = tiny
    FixedModeNLP(system, settings)
    assert kernels.wait()
    for library in _libraries(folder):
        raw = bytearray(library.read_bytes())
        raw[len(raw) // 2] ^= 0x01
        library.write_bytes(bytes(raw))
        kernels._STARTED.pop(library)  # as in a new process: its compile not started yet
    again = FixedModeNLP(system, settings)
    assert _stage_classes(again) == {"SXFunction"}  # none loaded
    assert kernels.wait()
    assert len(_libraries(folder)) == 13 and all(cbuild.verified(p) for p in _libraries(folder))
    assert _stage_classes(FixedModeNLP(system, settings)) == {"External"}


def test_a_sweeps_process_waits_for_its_kernels_once(tiny, monkeypatch):
    """A process running many runs (a sweep's: hmpc_cli.run.runner.run_one) compiles its
    kernels before its first solve, so even its first run evaluates them in C."""
    system, settings, folder = tiny
    monkeypatch.setattr(kernels, "_WAIT", True)
    nlp = FixedModeNLP(system, settings)
    assert _stage_classes(nlp) == {"External"} and len(_libraries(folder)) == 13


def test_the_reason_names_the_fallbacks_derivatives_of_an_sqp_solver(tiny):
    """sqp_hpipm solves its SX NLP on its Gauss-Newton Hessian; its IPOPT fallback gets the
    staged derivatives, and the build's reason says so (not the SQP's own functions, which
    have no kernels)."""
    system, settings, _ = tiny
    sqp = settings.model_copy(update={"solver": "sqp_hpipm", "input_hold": "zoh"})
    nlp = FixedModeNLP(system, sqp, switches=0)
    assert nlp.build_info.reason.endswith(
        "; derivatives of ipopt, the fallback, assembled stage by stage: stage kernels in SX "
        "(5 of 5)")  # held links and the last node: a gradient, 2 Jacobians, 2 Hessians
    assert nlp.session.cold.oracle().is_a("SXFunction")  # the transcription, for the SQP
    assert FixedModeNLP(system, settings.model_copy(update={"solver": "rti", "input_hold": "zoh"}),
                        switches=0).build_info.reason.count("stage by stage") == 0


@pytest.mark.parametrize("option", ["calc_lam_p", "detect_simple_bounds"])
def test_options_that_differentiate_the_nlp_itself_get_it_in_sx(tiny, option):
    """An nlpsol option that may make nlpsol differentiate the NLP itself (a post-solve
    quantity of ``nlp_grad``; the search for simple bounds), which C kernels cannot be:
    the NLP is then the SX transcription, IPOPT still given the staged derivatives, and
    it solves as the default build does."""
    system, settings, _ = tiny
    FixedModeNLP(system, settings)
    assert kernels.wait()  # the kernels in C from here on
    asked = FixedModeNLP(system, settings.model_copy(
        update={"solver_options": {option: True}}))
    assert asked.session.cold.oracle().is_a("SXFunction")
    assert asked.build_info.reason.endswith(
        "; derivatives assembled stage by stage: stage kernels in C (8)")
    default = FixedModeNLP(system, settings)
    for a, b in zip(_solves(default, system), _solves(asked, system), strict=True):
        assert a.stats.success and a.stats.iterations == b.stats.iterations
        np.testing.assert_array_equal(a.x, b.x)


def test_a_run_that_exits_mid_compile_leaves_nothing_behind(tiny, tmp_path):
    """A process that ends while its kernels compile stops the compiler at exit: no
    compiler outlives it, nothing is written into the cache directory after it, no
    partial output nor scratch directory is left, and its failure list stays empty (a
    stopped compile is not a failed one); a later process compiles the rest."""
    import os
    import subprocess
    import sys
    import time

    _, _, folder = tiny
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    script = ("import sys\n"
              "from hmpc_cli.core.registry import build_system\n"
              "from hmpc_cli.mpc import kernels\n"
              "from hmpc_cli.mpc.chain.nlp import FixedModeNLP\n"
              "from hmpc_cli.run.scenario import load_scenario\n"
              f"sc, _ = load_scenario({str(REPO / 'scenarios' / 'ball.toml')!r}, {TINY!r})\n"
              "FixedModeNLP(build_system(sc.system), sc.mpc)\n"
              "kernels._stop()\n"  # what exit runs first: then the failures are checked
              "sys.exit(3 if kernels._FAILED else 0)\n")
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120,
                   env={**os.environ, "TMPDIR": str(scratch)})
    after = sorted(p.name for p in folder.iterdir())
    assert not [name for name in after if name.startswith(".hmpc-")]
    assert len(_libraries(folder)) < len(KERNELS)  # it ended before compiling them all
    assert not list(scratch.iterdir())  # the compile's scratch directories removed
    time.sleep(1.0)  # a compiler still running would write its output now
    assert sorted(p.name for p in folder.iterdir()) == after
    system, settings, _ = tiny
    FixedModeNLP(system, settings)
    assert kernels.wait()
    assert len(_libraries(folder)) == len(KERNELS)
