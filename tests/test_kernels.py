"""Stage kernels compiled to C (hmpc_cli/mpc/kernels.py): the chain NLP's Hessian of the
Lagrangian evaluates its stages in C once a run has compiled them, with the numbers of the
SX kernels bit for bit; the cache off, nothing is compiled; a damaged library is never
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


def _stage_classes(nlp: FixedModeNLP) -> set[str]:
    """The kinds of function the IPOPT Hessian's stage maps call."""
    stages = {f.name(): f.class_name() for f in nlp.session.options["hess_lag"].find_functions()
              if f.class_name() != "Map"}
    assert set(stages) == {"link_foh_hess", "link_held_hess", "last_node_hess"}
    return set(stages.values())


def _solves(nlp: FixedModeNLP, ball) -> list:
    ns = NodeSchedule((0,), (), (nlp.N,))
    data = nlp.problem_data(ns, ChainLayout.build(ns, nlp.L), ball.x0)
    cold = nlp.optimize(np.zeros(nlp.nx_var), *data)
    return [cold, nlp.optimize(cold.x, *data, cold.lam_x, cold.lam_g)]


def test_a_second_build_evaluates_the_hessian_in_c_with_the_same_numbers(tiny):
    system, settings, folder = tiny
    first = FixedModeNLP(system, settings)  # compiles its kernels beside it
    assert kernels.wait()
    assert len(_libraries(folder)) == 3  # link with a first-order hold, held link, last node
    second = FixedModeNLP(system, settings)
    given = second.session.options["hess_lag"]
    sx = second._staged_hessian(second.layout)
    assert _stage_classes(second) == {"External"}  # the libraries are called
    assert _stage_classes(first) == {"SXFunction"}
    assert first.build_info.reason.endswith("; Hessian of the Lagrangian: stage kernels in "
                                            "SX (3 of 3)")
    assert second.build_info.reason.endswith("; Hessian of the Lagrangian: stage kernels in "
                                             "C (3)")
    rng = np.random.default_rng(0)
    for _ in range(5):
        args = [rng.standard_normal(second.nx_var), rng.uniform(size=second.np),
                rng.standard_normal(), rng.standard_normal(second.ng)]
        np.testing.assert_array_equal(given(*args).full(), sx(*args).full())
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
    assert len(_libraries(folder)) == 3 and all(cbuild.verified(p) for p in _libraries(folder))
    assert _stage_classes(FixedModeNLP(system, settings)) == {"External"}


def test_a_sweeps_process_waits_for_its_kernels_once(tiny, monkeypatch):
    """A process running many runs (a sweep's: hmpc_cli.run.runner.run_one) compiles its
    kernels before its first solve, so even its first run evaluates them in C."""
    system, settings, folder = tiny
    monkeypatch.setattr(kernels, "_WAIT", True)
    nlp = FixedModeNLP(system, settings)
    assert _stage_classes(nlp) == {"External"} and len(_libraries(folder)) == 3


def test_the_reason_names_the_fallbacks_hessian_of_an_sqp_solver(tiny):
    """sqp_hpipm solves on its Gauss-Newton Hessian; its IPOPT fallback gets the staged one,
    and the build's reason says so (not the SQP's own Hessian, which has no kernels)."""
    system, settings, _ = tiny
    sqp = settings.model_copy(update={"solver": "sqp_hpipm", "input_hold": "zoh"})
    nlp = FixedModeNLP(system, sqp, switches=0)
    assert nlp.build_info.reason.endswith(
        "; Hessian of the Lagrangian (of ipopt, the fallback): stage kernels in SX (2 of 2)")
    # (a zero-order hold: held links and the last node, no first-order-hold link)
    assert FixedModeNLP(system, settings.model_copy(update={"solver": "rti", "input_hold": "zoh"}),
                        switches=0).build_info.reason.count("Hessian") == 0
