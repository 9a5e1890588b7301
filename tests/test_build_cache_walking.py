"""The build cache serves the biped's walking NLP: compiled once, then loaded and solving
exactly as the SX build does.

A short walking NLP (6 intervals per swing) keeps the compile to seconds; slow (it runs
the C compiler).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hmpc_cli.mpc import cache
from hmpc_cli.mpc.walking.kind import WalkingMPC
from hmpc_cli.mpc.walking.nlp import WalkingNLP
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.scenario import load_scenario

REPO = Path(__file__).resolve().parents[1]
SHORT = ["mpc.nodes_per_swing=6", "mpc.apex_node=3"]

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def biped():
    """The biped and the short walking NLP's settings."""
    sc, _ = load_scenario(REPO / "scenarios" / "biped_stairs.toml", SHORT)
    return build_system(sc.system), sc.mpc


def _plan(system, settings, nlp: WalkingNLP):
    """A cold plan onto the first surface, then a warm re-solve of the same problem."""
    mpc = WalkingMPC(system, settings, nlp)
    target = min(mpc.segments)
    first = mpc.solve_segment(0.0, system.x0, target)
    return first, mpc.solve_segment(0.0, system.x0, target)


def test_walking_nlp_compiles_once_then_hits_and_solves_alike(biped, monkeypatch, tmp_path):
    system, settings = biped
    folder = tmp_path / "cache"
    folder.mkdir(mode=0o700)
    monkeypatch.setenv("HMPC_CACHE_DIR", str(folder))
    monkeypatch.setenv(cache.ENV, "sync")
    built = WalkingNLP(system, settings)
    assert built.build_info.cache == "miss" and not built.build_info.compiled
    assert built.build_info.reason.startswith("compiled nlp-")
    assert len(list(folder.glob("nlp-*.so"))) == 1
    loaded = WalkingNLP(system, settings)
    assert loaded.build_info.cache == "hit" and loaded.build_info.compiled
    for sx, compiled in zip(_plan(system, settings, built), _plan(system, settings, loaded),
                            strict=True):
        assert sx.stats.success and compiled.stats.success
        assert sx.stats.iterations == compiled.stats.iterations
        np.testing.assert_array_equal(compiled.traj.x, sx.traj.x)
        np.testing.assert_array_equal(compiled.traj.u, sx.traj.u)
    # another margin is another graph: it misses (built in SX, nothing loaded)
    monkeypatch.setenv(cache.ENV, "use")
    other = WalkingNLP(system, settings.model_copy(update={"terrain_margin": 0.03}))
    assert other.build_info.cache == "miss" and not other.build_info.compiled
