"""The MPC's build cache: same structure hits and solves alike, damage is caught, fallbacks.

A tiny chain (0.1 s horizon at 20 nodes/s, one switch) keeps the compiles to seconds; the
compiled entry is made once per module (``HMPC_BUILD_CACHE=sync``) and copied where a
test damages it.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from hmpc_cli.core import cbuild
from hmpc_cli.mpc import cache, kernels
from hmpc_cli.mpc.chain.layout import ChainLayout, NodeSchedule
from hmpc_cli.mpc.chain.nlp import FixedModeNLP, MPCSettings
from hmpc_cli.core.registry import build_system
from hmpc_cli.run.scenario import load_scenario
from conftest import nlp_function_calls

REPO = Path(__file__).resolve().parents[1]
TINY = ["mpc.horizon=0.1", "mpc.nodes_per_second=20", "mpc.max_switches=1"]


@pytest.fixture(scope="module")
def tiny():
    """The ball and the tiny chain's settings."""
    sc, _ = load_scenario(REPO / "scenarios" / "ball.toml", TINY)
    return build_system(sc.system), sc.mpc


@pytest.fixture(scope="module")
def filled(tiny, tmp_path_factory):
    """A cache directory holding the compiled tiny NLP, and the NLP of that first build."""
    folder = tmp_path_factory.mktemp("build-cache")
    folder.chmod(0o700)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HMPC_CACHE_DIR", str(folder))
        mp.setenv(cache.ENV, "sync")
        mp.setattr(kernels, "NICE", ())  # not starved by a loaded machine
        first = FixedModeNLP(*tiny)
        FixedModeNLP(*tiny, switches=0)  # the final domain's NLP: a second entry
        assert kernels.wait()  # its stage kernels' libraries, compiled beside it
    return folder, first


@pytest.fixture
def use(monkeypatch, tmp_path):
    """``use(folder=None, mode="sync")``: points the cache at a copy of ``folder``."""
    def point(folder: Path | None = None, mode: str = "sync") -> Path:
        target = tmp_path / "cache"
        if folder is not None:
            shutil.copytree(folder, target)
        target.mkdir(mode=0o700, exist_ok=True)
        target.chmod(0o700)
        monkeypatch.setenv("HMPC_CACHE_DIR", str(target))
        monkeypatch.setenv(cache.ENV, mode)
        return target
    return point


def _problem(nlp: FixedModeNLP, ball):
    """Parameters and bounds of a flow-only schedule in the ball's first mode."""
    ns = NodeSchedule((0,), (), (nlp.N,))
    return nlp.problem_data(ns, ChainLayout.build(ns, nlp.L), ball.x0)


def _solve_twice(nlp: FixedModeNLP, ball):
    """A cold solve and a warm re-solve from its result."""
    data = _problem(nlp, ball)
    cold = nlp.optimize(np.zeros(nlp.nx_var), *data)
    warm = nlp.optimize(cold.x, *data, cold.lam_x, cold.lam_g)
    return cold, warm


def test_first_build_misses_and_compiles(filled):
    _, first = filled
    assert first.build_info.cache == "miss" and not first.build_info.compiled
    assert "compiled" in first.build_info.reason


def test_same_problem_hits_and_solves_bit_identically(tiny, filled, use):
    folder, first = filled
    use(folder)
    second = FixedModeNLP(*tiny)
    assert second.build_info.cache == "hit" and second.build_info.compiled
    np.testing.assert_array_equal(second.layout.g["dynamics"], first.layout.g["dynamics"])
    for a, b in zip(_solve_twice(first, tiny[0]), _solve_twice(second, tiny[0]), strict=True):
        assert a.stats.success and b.stats.success
        assert a.stats.iterations == b.stats.iterations
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.lam_g, b.lam_g)
    w = np.linspace(0.0, 1.0, first.nx_var)
    p = _problem(first, tiny[0])[0]
    np.testing.assert_array_equal(first.constraints(w, p), second.constraints(w, p))


def test_the_library_holds_the_functions_ipopt_is_given_when_built(tiny, filled):
    """Built, the chain NLP gives IPOPT its functions assembled from stage kernels; the
    compiled library's are the same bit for bit at random points: its ``nlp_hess_l`` is the
    staged Hessian (its C), not one ``nlpsol`` derives from the whole graph (which differs
    with a first-order hold), the rest ``nlpsol``'s from the transcription."""
    import casadi as ca

    folder, first = filled
    assert set(first.session.derivatives) == {"grad_f", "jac_g", "hess_lag"}
    library = next(folder.glob(f"nlp-{cache.structure_key(*tiny, 1)[:32]}-*.so"))
    whole, _ = first._transcription()
    derived = ca.nlpsol("whole", "ipopt", whole, {"print_time": False, "no_nlp_grad": True,
                                                  "calc_lam_p": False})
    rng = np.random.default_rng(3)
    differs = 0
    for _ in range(5):
        for name, args in nlp_function_calls(rng, first.nx_var, first.np, first.ng):
            given = first.session.cold.get_function(name).call(args)
            compiled = ca.external(name, str(library)).call(args)
            for a, b in zip(given, compiled, strict=True):
                np.testing.assert_array_equal(a.full(), b.full(), err_msg=name)
        differs += np.count_nonzero(derived.get_function("nlp_hess_l").call(args)[0].full()
                                    != given[0].full())  # the last call: the Hessian
    assert differs > 0


def test_the_default_mode_writes_nothing_and_uses_a_stored_transcription(tiny, filled, use,
                                                                         monkeypatch):
    folder = use()  # an empty cache
    monkeypatch.delenv(cache.ENV)
    monkeypatch.setattr(kernels, "NICE", ())  # not starved by a loaded machine
    assert cache.mode() == "use"
    built = FixedModeNLP(*tiny)
    assert built.build_info.cache == "miss" and not built.build_info.compiled
    assert built.build_info.reason.startswith("not compiled: HMPC_BUILD_CACHE=background")
    assert kernels.wait()
    # a miss in the default mode writes nothing of the NLP (transcribing costs what loading
    # does), only its stage kernels' small libraries (hmpc_cli/mpc/kernels.py)
    assert {p.name.split("-")[0] for p in folder.iterdir()} == {"kernel"}
    # an entry another mode stored, its library not made yet: nothing rewritten
    stem = f"nlp-{cache.structure_key(*tiny, 1)[:32]}"
    for name in (f"{stem}.casadi", f"{stem}.casadi.sha256", f"{stem}-hess.casadi",
                 f"{stem}-hess.casadi.sha256", f"{stem}.json", f"{stem}.json.sha256"):
        shutil.copy(filled[0] / name, folder / name)
    stored = {p: p.read_bytes() for p in folder.iterdir()}
    # IPOPT's NLP assembled from stage kernels: the transcription verified, not loaded
    assembled = FixedModeNLP(*tiny)
    assert assembled.build_info.reason == f"{cache.TRANSCRIPTION_STORED}; " \
        f"{cache.NOT_COMPILED}; cost, rows and derivatives assembled stage by stage: stage " \
        "kernels in C (13)"
    # an option that needs nlpsol to differentiate the NLP itself: the transcription loaded
    # (the structure key leaves solver options out) and solved, IPOPT given the derivatives
    tiny_sx = (tiny[0], tiny[1].model_copy(update={"solver_options": {"calc_lam_p": True}}))
    loaded = FixedModeNLP(*tiny_sx)
    assert loaded.build_info.cache == "miss" and not loaded.build_info.compiled
    assert loaded.build_info.reason == f"{cache.TRANSCRIPTION_LOADED}; {cache.NOT_COMPILED}; " \
        "derivatives assembled stage by stage: stage kernels in C (8)"
    assert loaded.session.cold.oracle().is_a("SXFunction")
    assert {p: p.read_bytes() for p in folder.iterdir()} == stored  # nothing rewritten
    assert loaded.layout.to_dict() == assembled.layout.to_dict() == built.layout.to_dict()
    _, first = filled  # assembled: its solves are the loaded transcription's bit for bit
    for a, b in zip(_solve_twice(first, tiny[0]), _solve_twice(loaded, tiny[0]), strict=True):
        assert a.stats.success and a.stats.iterations == b.stats.iterations
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.lam_g, b.lam_g)
        np.testing.assert_array_equal(a.lam_x, b.lam_x)
    shutil.rmtree(folder)
    use(filled[0])  # a compiled entry is used in the default mode
    monkeypatch.delenv(cache.ENV)
    assert FixedModeNLP(*tiny).build_info.cache == "hit"


def test_changed_setting_misses_solver_option_hits(tiny):
    system, s = tiny
    key = cache.structure_key(system, s, 1)
    assert cache.structure_key(system, s, 1) == key
    for change in ({"horizon": 0.15}, {"integrator": "euler"}, {"input_hold": "zoh"},
                   {"soft_penalty": 1e3}):
        changed = MPCSettings(**{**s.model_dump(), **change})
        assert cache.structure_key(system, changed, 1) != key, change
    assert cache.structure_key(system, s, 0) != key
    applied = MPCSettings(**{**s.model_dump(), "max_iter": 7, "rate_hz": 20,
                             "tube_margin": 0.05})
    assert cache.structure_key(system, applied, 1) == key  # options, rates, margins
    sc, _ = load_scenario(REPO / "scenarios" / "ball.toml", [*TINY, "system.drag=0.03"])
    assert cache.structure_key(build_system(sc.system), s, 1) != key


def test_changed_setting_misses_the_filled_cache(tiny, filled, use):
    use(filled[0], mode="background")
    other = MPCSettings(**{**tiny[1].model_dump(), "max_iter": 30, "horizon": 0.15})
    assert cache.lookup(cache.structure_key(tiny[0], other, 1), "ipopt").info.cache == "miss"
    same = MPCSettings(**{**tiny[1].model_dump(), "max_iter": 30})
    hit = cache.lookup(cache.structure_key(tiny[0], same, 1), "ipopt")
    assert hit.info.cache == "hit" and hit.library is not None


@pytest.mark.parametrize("damage", ["truncate", "flip", "foreign"])
def test_damaged_library_is_detected_and_rebuilt(tiny, filled, use, caplog, damage):
    folder = use(filled[0])
    libs = sorted(folder.glob("nlp-*.so"))
    target = next(p for p in libs if cache.structure_key(tiny[0], tiny[1], 1)[:32] in p.name)
    if damage == "truncate":
        target.write_bytes(target.read_bytes()[: target.stat().st_size // 2])
    elif damage == "flip":
        raw = bytearray(target.read_bytes())
        raw[len(raw) // 2] ^= 0x01
        target.write_bytes(bytes(raw))
    else:  # another entry's library with its own (valid) record
        other = next(p for p in libs if p != target)
        shutil.copy(other, target)
        shutil.copy(cbuild.hash_path(other), cbuild.hash_path(target))
    with caplog.at_level(logging.WARNING, logger="hmpc_cli.mpc.cache"):
        nlp = FixedModeNLP(*tiny)
    assert "does not match its recorded sha256" in caplog.text
    assert nlp.build_info.cache == "miss" and "compiled" in nlp.build_info.reason
    assert _solve_twice(nlp, tiny[0])[0].stats.success
    again = FixedModeNLP(*tiny)  # the rebuilt library is used
    assert again.build_info.cache == "hit" and cbuild.verified(target)


def test_damaged_layout_is_detected(tiny, filled, use, caplog):
    folder = use(filled[0], mode="background")
    key = cache.structure_key(tiny[0], tiny[1], 1)
    meta = folder / f"nlp-{key[:32]}.json"
    meta.write_text(meta.read_text().replace('"size": ', '"size": 1', 1))
    with caplog.at_level(logging.WARNING, logger="hmpc_cli.mpc.cache"):
        hit = cache.lookup(key, "ipopt")
    assert hit.library is None and hit.info.cache == "miss"
    assert "does not match its recorded sha256" in caplog.text and not meta.exists()


@pytest.mark.parametrize("damage", ["flip", "foreign"])
def test_damaged_transcription_is_detected_and_transcribed_again(tiny, filled, use, caplog,
                                                                 damage):
    folder = use(filled[0], mode="use")
    for lib in folder.glob("nlp-*.so"):  # no library: the stored transcription is read
        lib.unlink()
    stem = f"nlp-{cache.structure_key(tiny[0], tiny[1], 1)[:32]}"
    target = folder / f"{stem}.casadi"
    if damage == "flip":
        raw = bytearray(target.read_bytes())
        raw[len(raw) // 2] ^= 0x01
        target.write_bytes(bytes(raw))
    else:  # the final domain's function with its own (valid) record
        other = next(p for p in folder.glob("nlp-*.casadi")
                     if p != target and not p.name.endswith("-hess.casadi"))
        shutil.copy(other, target)
        shutil.copy(cbuild.hash_path(other), cbuild.hash_path(target))
    with caplog.at_level(logging.WARNING, logger="hmpc_cli.mpc.cache"):
        nlp = FixedModeNLP(*tiny)
    assert "does not match its recorded sha256" in caplog.text
    assert "transcribing the NLP again" in caplog.text
    assert nlp.build_info.reason.startswith(f"{cache.NOT_COMPILED}; ")  # built anew
    assert _solve_twice(nlp, tiny[0])[0].stats.success
    assert not target.exists()  # removed, and the default mode stores no transcription
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="hmpc_cli.mpc.cache"):
        again = FixedModeNLP(*tiny)  # its layout left without a function: a quiet miss
    assert again.build_info.reason.startswith(f"{cache.NOT_COMPILED}; ") and not caplog.text


def test_a_missing_hessian_file_is_stored_again_and_compiled_with(tiny, filled, use, caplog):
    """An entry whose transcription is stored but whose Hessian file is gone (its layout
    file records one) is transcribed again, not loaded: the Hessian is written back and the
    library compiled with it, instead of every later compile failing on the missing file."""
    folder = use(filled[0], mode="sync")
    stem = f"nlp-{cache.structure_key(tiny[0], tiny[1], 1)[:32]}"
    for lib in folder.glob(f"{stem}-*.so"):
        lib.unlink()
    (folder / f"{stem}-hess.casadi").unlink()
    with caplog.at_level(logging.WARNING, logger="hmpc_cli.mpc.cache"):
        nlp = FixedModeNLP(*tiny)
    assert "-hess.casadi is missing or damaged: transcribing the NLP again" in caplog.text
    assert nlp.build_info.reason.startswith("compiled ")
    assert cbuild.verified(folder / f"{stem}-hess.casadi")
    again = FixedModeNLP(*tiny)
    assert again.build_info.cache == "hit" and again.build_info.compiled


def test_cache_writable_by_others_is_refused(tiny, filled, use):
    folder = use(filled[0])
    folder.chmod(0o777)
    nlp = FixedModeNLP(*tiny)
    assert nlp.build_info.cache == "disabled" and not nlp.build_info.compiled
    assert "writable by group or others" in nlp.build_info.reason
    assert _solve_twice(nlp, tiny[0])[0].stats.success


@pytest.mark.parametrize("how", ["missing CC", "empty PATH"])
def test_no_compiler_falls_back_to_sx_and_says_so(tiny, use, monkeypatch, how):
    use()
    if how == "missing CC":
        monkeypatch.setenv("CC", "/nonexistent/cc")
    else:
        monkeypatch.delenv("CC", raising=False)
        monkeypatch.setenv("PATH", "")
    nlp = FixedModeNLP(*tiny)
    info = nlp.build_info
    assert info.cache == "disabled" and not info.compiled
    assert ("cannot run /nonexistent/cc" if how == "missing CC" else "no C compiler") \
        in info.reason
    assert info.reason.endswith("stage kernels in SX (13 of 13)")  # no kernel compiled
    assert _solve_twice(nlp, tiny[0])[0].stats.success


def test_disabled_by_environment_writes_nothing(tiny, use, monkeypatch):
    folder = use()
    monkeypatch.setenv(cache.ENV, "off")
    nlp = FixedModeNLP(*tiny)
    assert nlp.build_info == cache.BuildInfo(
        "disabled", False, "HMPC_BUILD_CACHE=off: no NLP is compiled; cost, rows and "
        "derivatives assembled stage by stage: stage kernels in SX (13 of 13)")
    assert not os.listdir(folder)


def test_run_log_names_the_build(tiny, filled, use, run_hmpc, tmp_path):
    from hmpc_cli.log.rundata import read_run

    use(filled[0], mode="background")  # inherited by the hmpc process
    out = tmp_path / "run"
    res = run_hmpc(["run", str(REPO / "scenarios" / "ball.toml"), "--out", str(out),
                    "--quiet", "--set", "sim.duration=0.2",
                    *[a for t in TINY for a in ("--set", t)]], REPO)
    assert res.returncode in (0, 1), res.stderr
    build = read_run(out / "run.mcap").info.build
    assert build.cache == "hit" and build.compiled is True
    assert build.reason.startswith("loaded nlp-")


def test_sweep_says_when_its_nlps_are_not_compiled(tiny, filled, use, run_hmpc, tmp_path,
                                                   monkeypatch):
    """The default mode on an empty cache: a sweep whose NLPs ran in SX (the walking NLP,
    which has no stage kernels) notes the miss once and how to compile; one whose stage
    kernels ran in C (the chain NLP: its workers compile them first), or with the
    compiled entry (a hit), says nothing."""
    from hmpc_cli.log.rundata import read_run

    sets = "\n".join(f'"{k}" = {v}' for k, v in (t.split("=") for t in TINY))
    sweeps = {}
    for name, scenario, extra in (("tiny", "ball.toml", sets), ("biped", "biped_stairs.toml", "")):
        sweeps[name] = tmp_path / f"{name}.toml"
        sweeps[name].write_text(f'name = "{name}"\nscenario = "{REPO / "scenarios" / scenario}"'
                                f'\nseeds = 2\n[set]\n"sim.duration" = 0.1\n{extra}\n')
    use(filled[0], mode="use")  # inherited by the hmpc process
    empty = tmp_path / "empty-cache"
    empty.mkdir(mode=0o700)
    for folder, sweep, noted in ((None, "tiny", False), (empty, "tiny", False),
                                 (empty, "biped", True)):
        if folder is not None:
            monkeypatch.setenv("HMPC_CACHE_DIR", str(folder))
        out = tmp_path / f"out-{sweep}-{noted}-{folder is None}"
        res = run_hmpc(["sweep", str(sweeps[sweep]), "--out", str(out), "--quiet"], REPO)
        assert res.returncode == 0, res.stderr
        text = " ".join((res.stdout + res.stderr).split())
        note = "note: the MPC's NLPs of this sweep are not compiled (build cache miss)"
        assert (note in text) is noted and text.count(note) <= 1
        if noted:
            assert (f"HMPC_BUILD_CACHE=sync hmpc run {out / 'runs'}") in text
            assert "--set sim.duration=0.1" in text
        elif folder is not None:  # the chain NLP's stage kernels ran in C
            run = next(out.glob("runs/**/run.mcap"))
            assert "stage kernels in C (13)" in read_run(run).info.build.reason


def test_background_compile_after_exit_fills_the_cache(tiny, use):
    import subprocess
    import sys
    import time

    folder = use(mode="background")
    code = ("from hmpc_cli.core.registry import build_system; from hmpc_cli.run.scenario import "
            "load_scenario; from hmpc_cli.mpc.chain.nlp import FixedModeNLP; import sys; "
            f"sc, _ = load_scenario(sys.argv[1], {TINY!r}); "
            "n = FixedModeNLP(build_system(sc.system), sc.mpc); print(n.build_info.reason)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get(
        "PYTHONPATH", "")])}
    res = subprocess.run([sys.executable, "-c", code, str(REPO / "scenarios" / "ball.toml")],
                         env=env, capture_output=True, text=True, timeout=120, check=True)
    assert "compiled in the background when this process exits" in res.stdout
    key = cache.structure_key(*tiny, 1)
    deadline = time.monotonic() + 120
    while list(folder.glob("*.lock")) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not list(folder.glob("*.failed"))
    hit = cache.lookup(key, "ipopt")
    assert hit.info.cache == "hit" and hit.library is not None


def test_layout_round_trips_through_json(filled):
    import json

    from hmpc_cli.mpc.builder import NLPLayout

    layout = filled[1].layout
    back = NLPLayout.from_dict(json.loads(json.dumps(layout.to_dict())))
    for kind in "xpg":
        a, b = getattr(layout, kind), getattr(back, kind)
        assert a.size == b.size and a.names == b.names
        for name in a.names:
            np.testing.assert_array_equal(a[name], b[name])
            assert a.stages(name) == b.stages(name)
        np.testing.assert_array_equal(a.at(0), b.at(0))


def test_stale_temporaries_are_removed(tmp_path):
    old, new = tmp_path / ".hmpc-old.so", tmp_path / ".hmpc-new.so"
    old.write_bytes(b"partial")
    new.write_bytes(b"in progress")
    os.utime(old, (1.0, 1.0))
    assert cbuild.remove_stale_temporaries(tmp_path) == 1
    assert not old.exists() and new.exists()


def test_the_sweep_note_counts_every_nlps_kernels(monkeypatch, tmp_path):
    """A run's build reason joins its NLPs': the note is left out only when none of them
    ran a stage kernel in SX (one NLP's kernels in C do not speak for the other's)."""
    import hmpc_cli.log.reader as reader
    from hmpc_cli.cli.sweep import not_compiled_note
    from hmpc_cli.mpc.kernels import IN_C, IN_SX

    for reason, noted in ((f"not compiled: x; {IN_C} (13)", False),
                          (f"not compiled: x; {IN_SX} (5 of 13); not compiled: x; {IN_C} (13)",
                           True),
                          (f"not compiled: x; {IN_SX} (13 of 13)", True)):
        monkeypatch.setattr(reader, "first_message", lambda path, topic, r=reason: {
            "build": {"cache": "miss", "compiled": False, "reason": r}})
        assert bool(not_compiled_note(tmp_path)) is noted, reason
