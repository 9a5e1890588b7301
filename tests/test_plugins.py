"""System plug-ins from outside the package, through the documented entry-point mechanism.

``tests/plugins`` holds a distribution the way pip installs one: the module
``hmpc_dock.py`` and ``hmpc_dock-0.1.dist-info/`` (``METADATA`` and ``entry_points.txt``,
``[hmpc.systems] dock = hmpc_dock:SYSTEM``). importlib.metadata finds ``*.dist-info``
directories on sys.path, so ``hmpc`` with ``PYTHONPATH=tests/plugins`` loads the dock
exactly as it loads an installed package's system. Every run goes through the real
command line in a fresh process (the registry is built once per process).
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
from importlib.metadata import distributions
from pathlib import Path

import numpy as np
import pytest

from conftest import BALL, REPO, cli_env, hmpc_command, standard_schema_errors
from hmpc_cli.analysis.replay import _ignored
from hmpc_cli.core.numeric import supported_operations
from hmpc_cli.log.reader import read_log

PLUGINS = REPO / "tests" / "plugins"
DOCK = PLUGINS / "dock.toml"


def hmpc(args: list[str], *paths: Path, cwd: Path, timeout: float = 300
         ) -> subprocess.CompletedProcess:
    """``hmpc ARGS`` in a fresh process with ``paths`` in front of PYTHONPATH."""
    env = cli_env()
    env["PYTHONPATH"] = os.pathsep.join(
        [str(p) for p in paths] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return subprocess.run([*hmpc_command(), *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


def error_lines(proc: subprocess.CompletedProcess) -> list[str]:
    return [line for line in proc.stderr.splitlines() if line.strip()]


def write_dist(root: Path, name: str, entry_points: str, modules: dict[str, str]) -> Path:
    """A distribution directory as pip leaves it: modules + NAME-0.1.dist-info."""
    info = root / f"{name.replace('-', '_')}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(entry_points)
    for module, text in modules.items():
        (root / f"{module}.py").write_text(text)
    return root


def test_the_dock_distribution_is_an_ordinary_entry_point():
    (dist,) = [d for d in distributions(path=[str(PLUGINS)])]
    assert dist.metadata["Name"] == "hmpc-dock"
    (ep,) = dist.entry_points.select(group="hmpc.systems")
    assert (ep.name, ep.value) == ("dock", "hmpc_dock:SYSTEM")


@pytest.fixture(scope="module")
def dock_run(tmp_path_factory) -> Path:
    """``PYTHONPATH=tests/plugins hmpc run tests/plugins/dock.toml``: its output directory."""
    out = tmp_path_factory.mktemp("dock") / "dock"
    proc = hmpc(["run", str(DOCK), "--out", str(out), "-q"], PLUGINS, cwd=out.parent)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def test_the_guides_worked_example_as_written_is_the_tested_plugin(tmp_path, dock_run):
    """docs/plugins.md's worked example laid out as the guide says (``my_pkg/dock.py``
    from its Python block, the entry point from its pyproject table, as pip would write
    it, and its ``dock.toml``) runs through ``hmpc run``, and flies exactly the run of
    tests/plugins/hmpc_dock.py (the guide's shortened code is the same system)."""
    import re
    import tomllib

    text = (REPO / "docs" / "plugins.md").read_text()
    code = next(b for b in re.findall(r"```python\n(.*?)```", text, re.S)
                if b.startswith("# my_pkg/dock.py"))
    tomls = re.findall(r"```toml\n(.*?)```", text, re.S)
    project = tomllib.loads(next(b for b in tomls if "[project]" in b))["project"]
    scenario = next(b for b in tomls if b.startswith("# dock.toml"))
    (tmp_path / "my_pkg").mkdir()
    (tmp_path / "my_pkg" / "__init__.py").write_text("")
    (tmp_path / "my_pkg" / "dock.py").write_text(code)
    info = tmp_path / f"{project['name'].replace('-', '_')}-{project['version']}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\n"
                                   f"Version: {project['version']}\n")
    (info / "entry_points.txt").write_text("".join(
        f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items())
        for group, eps in project["entry-points"].items()))
    (tmp_path / "dock.toml").write_text(scenario)
    out = tmp_path / "out"
    proc = hmpc(["run", "dock.toml", "--out", str(out), "-q"], tmp_path, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]

    def flown(run: Path) -> dict:  # the summary but its measured times and the machine
        s = json.loads((run / "summary.json").read_text())
        return {k: v for k, v in s.items() if not _ignored(k)}

    guide, tested = flown(out), flown(dock_run)
    assert guide["success"] and guide["contacts_by_guard"] == {"bumper": 1, "dock": 1}
    assert guide == tested
    # the guide's words: it docks at t = 0.82 s, ends 5e-5 from the goal, 31 solves
    events = read_log(out / "run.mcap").topic("/sim/event")
    assert [(m.data["guard_name"], round(m.data["t"], 2)) for m in events] == [
        ("bumper", 0.24), ("dock", 0.82)]
    assert f"{guide['final_error']:.0e}" == "5e-05" and guide["solves"] == 31


def test_dock_runs_through_the_cli(dock_run):
    out = dock_run
    s = json.loads((out / "summary.json").read_text())
    assert s["success"], s["reason"]
    assert s["mode_end"] == "docked"
    # it starts at p = 1 moving left at 4 m/s and brakes at 5 N at most: the bumper is
    # unavoidable, then the dock's latch, then it stops at the goal
    assert s["contacts_by_guard"] == {"bumper": 1, "dock": 1}
    assert s["solver_failures"] == 0 and s["planner_rejected"] == 0
    p, v = s["x_end"]
    assert math.isclose(s["final_error"], math.hypot(p - 2.5, v), abs_tol=1e-12)
    assert s["final_error"] <= 0.2

    log = read_log(out / "run.mcap")
    info = log.topic("/run/info")[0].data
    assert info["system"] == "dock"
    assert info["guard_names"] == ["dock", "bumper"]
    assert info["mode_names"] == ["free", "docked"]
    assert info["state_names"] == ["p", "v"]
    scenario = json.loads(info["scenario_json"])
    assert scenario["system"]["name"] == "dock"
    # the plug-in's planner defaults (SystemSpec.defaults["planner.cem"]) were applied
    assert scenario["planner"]["kind"] == "cem"
    assert scenario["planner"]["horizon"] == 2.0
    assert scenario["planner"]["knots"] == 10
    (plan,) = log.topic("/planner/plan")
    assert plan.data["schedule"]["guard_names"] == ["bumper", "dock"]
    events = [(m.data["guard_name"], m.data["scheduled"]) for m in log.topic("/sim/event")]
    assert events == [("bumper", True), ("dock", True)]
    assert standard_schema_errors(log) == []  # the plug-in's log, by jsonschema too


def test_schema_lists_the_plugin_only_when_it_is_installed(tmp_path):
    proc = hmpc(["schema"], PLUGINS, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    schema = json.loads(proc.stdout)
    mapping = schema["properties"]["system"]["discriminator"]["mapping"]
    assert set(mapping) >= {"ball", "biped", "dock"}
    dock = schema["$defs"][mapping["dock"].rsplit("/", 1)[1]]["properties"]
    assert {"u_free", "u_docked", "damping", "dock_at", "catch", "restitution",
            "success_radius"} <= set(dock)
    assert dock["u_free"]["description"].startswith("input bound")

    bare = hmpc(["schema"], cwd=tmp_path)
    assert bare.returncode == 0, bare.stderr[-3000:]
    assert "dock" not in json.loads(bare.stdout)["properties"]["system"]["discriminator"][
        "mapping"]
    run = hmpc(["run", str(DOCK), "--out", str(tmp_path / "none"), "-q"], cwd=tmp_path)
    assert run.returncode == 2
    assert error_lines(run) == [f"error: {DOCK}: system.name: unknown system 'dock' "
                                "(choose from 'ball', 'biped')"]


BROKEN = [
    ("broken", "hmpc_broken:SYSTEM",
     "failed to load: ImportError: hmpc_broken needs the missing package libcart"),
    ("ghost", "hmpc_dock:NO_SUCH_SPEC",
     "failed to load: AttributeError: module 'hmpc_dock' has no attribute 'NO_SUCH_SPEC'"),
]


@pytest.fixture
def broken_dist(tmp_path) -> Path:
    eps = "[hmpc.systems]\n" + "".join(f"{n} = {v}\n" for n, v, _ in BROKEN)
    return write_dist(tmp_path / "site", "hmpc-broken", eps, {
        "hmpc_broken": 'raise ImportError("hmpc_broken needs the missing package libcart")\n'})


@pytest.mark.parametrize("name, value, reason", BROKEN, ids=[b[0] for b in BROKEN])
def test_a_broken_plugin_is_one_error_line(tmp_path, broken_dist, name, value, reason):
    scenario = tmp_path / f"{name}.toml"
    scenario.write_text(f'[system]\nname = "{name}"\n')
    out = tmp_path / "out"
    proc = hmpc(["run", str(scenario), "--out", str(out), "-q"], broken_dist, PLUGINS,
                cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert error_lines(proc) == [
        f"error: {scenario}: system.name: entry point {name!r} = {value!r} "
        f"(group hmpc.systems) {reason}"]
    assert not out.exists()


@pytest.mark.slow
def test_the_others_still_run_beside_a_broken_plugin(tmp_path, broken_dist):
    out = tmp_path / "ball"
    proc = hmpc(["run", str(BALL), "--set", "sim.duration=0.2", "--out", str(out), "-q"],
                broken_dist, PLUGINS, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    assert s["t_end"] == pytest.approx(0.2) and s["solves"] >= 1 and s["solver_failures"] == 0
    assert read_log(out / "run.mcap").topic("/run/info")[0].data["system"] == "ball"


FAULTY = """
from hmpc_dock import SYSTEM, DockParams, build_dock
from dataclasses import replace
from typing import Literal

import casadi as ca


class BadBuild(DockParams):
    name: Literal["badbuild"] = "badbuild"


class Liar(DockParams):
    name: Literal["liar"] = "liar"


def _fail(p):
    raise ValueError("dock_at must lie inside the track")


class BadShape(DockParams):
    name: Literal["badshape"] = "badshape"


def _three_states(p):
    import numpy as np

    dock = build_dock(DockParams(**{**p.model_dump(), "name": "dock"}))
    return replace(dock, x0=np.zeros(3), tracking_gain=lambda kp, kd: np.zeros((1, 3)))


BAD_BUILD = replace(SYSTEM, name="badbuild", params=BadBuild, build=_fail)
BAD_SHAPE = replace(SYSTEM, name="badshape", params=BadShape, build=_three_states)
LIAR = replace(SYSTEM, name="liar", params=Liar,
               build=lambda p: build_dock(DockParams(**{**p.model_dump(), "name": "dock"})),
               provides=frozenset({"stance_foot"}))


class ErfFlow(DockParams):
    name: Literal["erfflow"] = "erfflow"


class NoTask(DockParams):
    name: Literal["notask"] = "notask"


class TrueVerdict(DockParams):
    name: Literal["trueverdict"] = "trueverdict"


def _dock(p):
    return build_dock(DockParams(**{**p.model_dump(), "name": "dock"}))


def _erf_flow(p):
    dock = _dock(p)
    x, u, w = ca.SX.sym("x", 2), ca.SX.sym("u", 1), ca.SX.sym("w", 1)
    free = replace(dock.modes[0], flow=ca.Function("f_erf", [x, u, w], [
        ca.vertcat(x[1], ca.erf(u) + w)]))
    return replace(dock, modes=(free, *dock.modes[1:]))


class Agrees:
    goal = (2.5, 0.0)

    def failure(self, x, mode):
        return ""

    def verdict(self, x, mode):
        return True


ERF = replace(SYSTEM, name="erfflow", params=ErfFlow, build=_erf_flow)
NO_TASK = replace(SYSTEM, name="notask", params=NoTask, build=_dock,
                  task=lambda p, system: None)
TRUE = replace(SYSTEM, name="trueverdict", params=TrueVerdict, build=_dock,
               task=lambda p, system: Agrees())


class TypoDefault(DockParams):
    name: Literal["typodefault"] = "typodefault"


class TypoRequire(DockParams):
    name: Literal["typorequire"] = "typorequire"


from hmpc_cli.plugin import Requirement

class WrongSign(DockParams):
    name: Literal["wrongsign"] = "wrongsign"


def _wrong_sign(p):
    dock = _dock(p)
    x = ca.SX.sym("x", 2)
    flipped = replace(dock.guards[0], nlp_gap=ca.Function("q_dock", [x], [x[0] - p.dock_at]))
    return replace(dock, guards=(flipped, *dock.guards[1:]))


WRONG_SIGN = replace(SYSTEM, name="wrongsign", params=WrongSign, build=_wrong_sign)


class NanGap(DockParams):
    name: Literal["nangap"] = "nangap"


def _nan_gap(p):
    dock = _dock(p)
    x = ca.SX.sym("x", 2)
    dock_guard = replace(dock.guards[0], nlp_gap=ca.Function("q_dock", [x], [
        ca.sqrt(x[0] - p.dock_at)]))
    bumper = replace(dock.guards[1], h=ca.Function("h_bumper", [x], [1 / (x[0] - 1.0)]))
    return replace(dock, guards=(dock_guard, bumper))


NAN_GAP = replace(SYSTEM, name="nangap", params=NanGap, build=_nan_gap)


class DrawnCart(DockParams):
    name: Literal["drawncart"] = "drawncart"


def _drawn_cart(p):
    import numpy as np

    from hmpc_cli.plugin import Drawing

    drawing = Drawing(points=lambda x: np.array([[x[0], x[0] + 0.2], [0.1, 0.1]]),
                      point_names=("cart", "hook"), links=(("cart", "hook"),))
    return replace(_dock(p), drawing=drawing)


DRAWN_CART = replace(SYSTEM, name="drawncart", params=DrawnCart, build=_drawn_cart)


class Regioned(DockParams):
    name: Literal["regioned"] = "regioned"


def _regioned(p):
    dock = _dock(p)
    x = ca.SX.sym("x", 2)
    latch = replace(dock.guards[0], region=ca.Function("r_dock", [x], [x[1]]))  # v >= 0
    return replace(dock, guards=(latch, *dock.guards[1:]))


REGIONED = replace(SYSTEM, name="regioned", params=Regioned, build=_regioned)
TYPO_DEFAULT = replace(SYSTEM, name="typodefault", params=TypoDefault, build=_dock,
                       defaults={**SYSTEM.defaults, "sim": {"rat_hz": 600}, "planner.cem": {
                           **SYSTEM.defaults["planner.cem"], "sampels": 30},
                                 "mpc.chain": {"horizon": 2.0}, "sensor": {"rate": 1}})
TYPO_REQUIRE = replace(SYSTEM, name="typorequire", params=TypoRequire, build=_dock,
                       requires=(Requirement("mpc.nodes_per_secnd", 60, "fine grid"),))
"""


def _faulty_site(tmp_path: Path) -> Path:
    """The FAULTY plug-ins installed in ``tmp_path/site``."""
    names = {"badbuild": "BAD_BUILD", "liar": "LIAR", "badshape": "BAD_SHAPE",
             "erfflow": "ERF", "notask": "NO_TASK", "trueverdict": "TRUE",
             "typodefault": "TYPO_DEFAULT", "typorequire": "TYPO_REQUIRE",
             "wrongsign": "WRONG_SIGN", "nangap": "NAN_GAP", "drawncart": "DRAWN_CART",
             "regioned": "REGIONED"}
    return write_dist(tmp_path / "site", "hmpc-faulty", "[hmpc.systems]\n" + "".join(
        f"{k} = hmpc_faulty:{v}\n" for k, v in names.items()), {"hmpc_faulty": FAULTY})


@pytest.mark.parametrize("name, reason", [
    ("badbuild", "system: 'badbuild' failed to build: ValueError: dock_at must lie inside "
                 "the track"),
    ("liar", "system: 'liar' declares that it provides stance_foot, but its HybridSystem "
             "has none"),
    # a part of the wrong size is named when the system is built, not inside a run
    ("badshape", "system: 'badshape' failed to build: ValueError: dock: x0 has shape (3,), "
                 "expected (2,) (one entry per state ['p', 'v']); tracking_gain(kp, kd) "
                 "must be 1 x 2 (inputs x states), not 1 x 3"),
    # an operation the NumPy evaluators lack, a task that is not one: before the run
    ("erfflow", "system: 'erfflow' failed to build: ValueError: dock: f_erf uses erf: "
                "CasADi operations the simulator's and planner's NumPy evaluators cannot "
                f"run (they run {', '.join(supported_operations())}; 'call' is a Function "
                "called inside, e.g. an interpolant or a Callback)"),
    ("notask", "system: the task of 'notask' is a NoneType without a method failure(x, "
               "mode), a method verdict(x, mode), a goal (a task has goal, failure(x, mode) "
               "-> str and verdict(x, mode) -> Verdict: docs/plugins.md)"),
    ("trueverdict", "system: the task of 'trueverdict': verdict(x0, mode) returned a bool, "
                    "not a Verdict"),
    # an nlp_gap of the wrong sign would turn the NLP's guard-avoid rows around
    ("wrongsign", "system: guard 'dock' of mode 'free': nlp_gap(x0) = -1 has the opposite "
                  "sign to its gap at x0 (1 = -direction (h(x0) - level), h(x0) = 1, level "
                  "2, direction +1): the NLP's gap must be positive where the guard's gap "
                  "is, before the crossing (docs/plugins.md)"),
    # a gap that is NaN or inf at x0 (a guard that would never fire), each guard named
    ("nangap", "\n".join(
        f"system.x0: guard {name!r} of mode 'free' is not finite at x0 (1, -4): {what}: a "
        "gap that is NaN or inf never fires in the simulator and makes the NLP's rows NaN; "
        "check the guard's expression where x0 lies (a square root of a negative number, "
        "a division by 0), or move system.x0"
        for name, what in (("dock", "nlp_gap(x0) = nan"), ("bumper", "h(x0) = inf")))),
])
def test_a_plugin_that_fails_to_build_is_one_error_line(tmp_path, name, reason):
    """Named when the run is built (exit 2, nothing written), not inside it; a sweep
    names it in its check of every cell before its first run."""
    site = _faulty_site(tmp_path)
    scenario = tmp_path / f"{name}.toml"
    scenario.write_text(f'[system]\nname = "{name}"\n')
    out = tmp_path / "out"
    proc = hmpc(["run", str(scenario), "--out", str(out), "-q"], site, PLUGINS, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    assert error_lines(proc) == [f"error: {scenario}: {line}" for line in reason.split("\n")]
    assert not out.exists()
    (tmp_path / "s.toml").write_text(f'name = "s"\nscenario = "{scenario.name}"\nseeds = 1\n')
    proc = hmpc(["sweep", "s.toml", "--out", str(out)], site, PLUGINS, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert error_lines(proc) == [f"error: s.toml: cell the base scenario: {line}"
                                 for line in reason.split("\n")]
    assert not out.exists()


def test_fig4_of_a_system_without_the_walkers_points_says_what_it_needs(tmp_path):
    """A run that logs body points but no terrain, hip or swing_foot: fig4 names all three
    and the points it logs."""
    site = _faulty_site(tmp_path)
    scenario = tmp_path / "drawncart.toml"
    scenario.write_text('[system]\nname = "drawncart"\n[sim]\nduration = 0.2\n')
    out = tmp_path / "run"
    proc = hmpc(["run", str(scenario), "--out", str(out), "-q"], site, PLUGINS, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    proc = hmpc(["plot", "fig4", str(out), "--out", str(tmp_path / "fig")], site, PLUGINS,
                cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert error_lines(proc) == [
        f"error: {out / 'run.mcap'}: not a walking run to draw (fig4 needs the terrain and "
        "the body points named 'hip' and 'swing_foot'; system 'drawncart' logs no terrain, "
        "no body point 'hip', no body point 'swing_foot' (its body points: 'cart', 'hook'))"]


def test_a_guard_region_x0_lies_outside_where_its_avoid_row_fails_is_warned_of(tmp_path):
    """The fixed-mode MPC imposes the dock's guard-avoid row q >= kappa at every node of
    mode free, outside the dock's region (v >= 0) too: with the dock 5 mm ahead of x0
    (q = 0.005 < kappa = 0.01) the summary warns; 1 m ahead it does not."""
    site = _faulty_site(tmp_path)
    warnings = {}
    for dock_at in (1.005, 2.0):
        scenario = tmp_path / f"regioned{dock_at}.toml"
        scenario.write_text(f'[system]\nname = "regioned"\ndock_at = {dock_at}\n[sim]\n'
                            'duration = 0.1\n[mpc]\ntube_margin = 0.01\n')
        out = tmp_path / f"run{dock_at}"
        proc = hmpc(["run", str(scenario), "--out", str(out), "-q"], site, PLUGINS,
                    cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr[-3000:]
        warnings[dock_at] = json.loads((out / "summary.json").read_text())["warnings"]
    assert warnings == {1.005: [
        "system: guard 'dock' of mode 'free': x0 lies outside its region and its guard-avoid "
        "row fails there (nlp_gap(x0) = 0.005, kappa = 0.01): the fixed-mode MPC imposes that "
        "row at every node of mode 'free', outside the region too, so solves are softened or "
        "infeasible; fold the region into the guard's nlp_gap (docs/plugins.md)"], 2.0: []}


def test_a_plugins_own_misspelled_default_or_requirement_is_blamed_on_it(tmp_path):
    """A key a plug-in's defaults or requires set that its section lacks is the plug-in's
    mistake: named at system.name with the fix, not as an unknown key of the scenario."""
    site = _faulty_site(tmp_path)
    fix = "the plug-in must be fixed, not the scenario"
    for name, lines in {
        "typodefault": [
            # the key's whole path in the defaults, the kind's table included
            "system.name: the system plug-in 'typodefault' sets planner.cem.sampels in its "
            "SystemSpec.defaults, which is not a setting of [planner.cem] (did you mean "
            f"'samples'?); {fix}",
            "system.name: the system plug-in 'typodefault' sets sim.rat_hz in its "
            f"SystemSpec.defaults, which is not a setting of [sim] (did you mean 'rate_hz'?); "
            f"{fix}",
            "system.name: the system plug-in 'typodefault' sets [sensor] in its "
            "SystemSpec.defaults, which is no section a plug-in may set (sections: sim, "
            f"disturbance, replanning, lowlevel, planner.<kind>, mpc.<kind>); {fix}"],
        "typorequire": [
            "system.name: the system plug-in 'typorequire' sets mpc.nodes_per_secnd in its "
            "SystemSpec.requires, which is not a setting of [mpc] (did you mean "
            f"'nodes_per_second'?); {fix}"]}.items():
        scenario = tmp_path / f"{name}.toml"
        scenario.write_text(f'[system]\nname = "{name}"\n')
        proc = hmpc(["run", str(scenario), "--out", str(tmp_path / "out"), "-q"], site,
                    PLUGINS, cwd=tmp_path)
        assert proc.returncode == 2, proc.stderr[-3000:]
        assert error_lines(proc) == [f"error: {scenario}: {line}" for line in lines]
        assert not (tmp_path / "out").exists()


def test_a_planner_that_does_not_fit_names_planner_kind(tmp_path):
    out = tmp_path / "out"
    proc = hmpc(["run", str(DOCK), "--set", "planner.kind=footholds", "--out", str(out), "-q"],
                PLUGINS, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    lines = error_lines(proc)
    # the --set that chose the kind is named as the source
    assert lines == ["error: --set planner.kind=footholds: planner.kind: 'footholds' does not "
                     "fit system 'dock': it needs WalkerModel, guard_surfaces (use 'cem')"]
    assert not out.exists()


# ------------------------------------------------------------------ geometry of a system
CENTRE, RADIUS = (4.0, 2.5), 0.8


def circle_points(fig, centre, radius, tol) -> np.ndarray:
    """Angles [rad] of the drawn points of every line or path (contours included) that lies
    on the circle |p - centre| = radius within tol (whole artists/paths only)."""
    c = np.asarray(centre, dtype=float)
    angles = []
    for ax in fig.axes:
        polylines = [line.get_xydata() for line in ax.lines]
        for coll in ax.collections:
            to_data = coll.get_transform() - ax.transData
            polylines += [to_data.transform(p.vertices) for p in coll.get_paths()]
        for xy in polylines:
            xy = np.asarray(xy, dtype=float)
            xy = xy[np.isfinite(xy).all(axis=1)]
            if len(xy) >= 8 and np.all(np.abs(np.linalg.norm(xy - c, axis=1) - radius) <= tol):
                angles.append(np.arctan2(xy[:, 1] - c[1], xy[:, 0] - c[0]))
    return np.concatenate(angles) if angles else np.zeros(0)


@pytest.mark.slow
def test_changed_ball_geometry_is_used_logged_and_drawn(tmp_path, monkeypatch):
    sweep = tmp_path / "sweep"
    out = sweep / "runs" / "geo"
    proc = hmpc(["run", str(BALL), "--set", f"system.circle_center=[{CENTRE[0]}, {CENTRE[1]}]",
                 "--set", f"system.circle_radius={RADIUS}", "--out", str(out), "-q"],
                cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    s = json.loads((out / "summary.json").read_text())
    # (a) the task judges the new circle: error to its centre, success within its radius
    dist = math.hypot(s["x_end"][0] - CENTRE[0], s["x_end"][1] - CENTRE[1])
    assert math.isclose(s["final_error"], dist, rel_tol=1e-9, abs_tol=1e-12)
    assert s["success"] == (s["final_error"] <= RADIUS)
    assert s["success"], s["reason"]
    assert s["mode_end"] == "inside" and s["contacts_by_guard"].get("circle_in") == 1
    # (b) the log's scenario holds the new geometry
    info = json.loads(read_log(out / "run.mcap").topic("/run/info")[0].data["scenario_json"])
    assert info["system"]["circle_center"] == list(CENTRE)
    assert info["system"]["circle_radius"] == RADIUS

    # (c) Figure 3 from a sweep directory (what `hmpc plot fig3 SWEEP_DIR` reads) draws the
    # new circle, not the default one; the figure is taken where it is saved
    with open(sweep / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["controller", "disturbance", "success", "log"])
        w.writerow(["10 Hz fixed", "nominal", s["success"], "runs/geo/run.mcap"])
    from matplotlib.figure import Figure

    from hmpc_cli.figures.fig3 import fig3

    saved = []
    original = Figure.savefig

    def savefig(self, *args, **kwargs):
        saved.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", savefig)
    fig3(sweep, tmp_path / "fig", formats=("png",), dpi=50)
    assert (tmp_path / "fig" / "fig3.png").is_file()
    assert saved
    angles = circle_points(saved[0], CENTRE, RADIUS, tol=0.01)
    covered = np.unique(np.floor((angles + np.pi) / (2 * np.pi) * 36).astype(int) % 36)
    assert len(covered) == 36, f"the new circle is not drawn whole ({len(covered)}/36 sectors)"
    assert circle_points(saved[0], (3.0, 3.0), 1.0, tol=0.01).size == 0, \
        "the default circle is drawn"


TOY_KINDS = '''"""A toy planner and a toy MPC kind: settings subclass the plug-in bases."""
from typing import Literal

import numpy as np

from hmpc_cli.plugin import (
    MPCKindSettings, MPCSpec, ModeSchedule, Plan, PlannerResult, PlannerSettings,
    PlannerSpec, SolveStats, Trajectory)


class StaySettings(PlannerSettings):
    kind: Literal["stay"] = "stay"

    def system_problems(self, system):
        return [] if system.final_mode else ["planner.kind: no final mode to stay in"]


class Stay:
    def plan(self, t, x, mode, solve):
        return PlannerResult(ModeSchedule.final(mode, t), None, 0.0, False, 0.0, 1)


class HoldSettings(MPCKindSettings):
    kind: Literal["hold"] = "hold"
    rate_hz: int = 10
    u: float = 0.0

    def scenario_problems(self):
        return [] if abs(self.u) < 1e3 else ["mpc.u: at most 1e3"]

    def resolves_on_impact(self):
        return False


class Hold:
    def __init__(self, system, settings):
        self.system, self.s, self.rate_hz = system, settings, settings.rate_hz

    def check(self, schedule):
        return ""

    def solve(self, t, x, mode, schedule, events=(), guess=None):
        ts = np.array([0.0, 1.0])
        traj = Trajectory(ts, np.vstack([x, x]), np.full((2, self.system.n_u), self.s.u),
                          np.array([mode, mode]), np.zeros(2, dtype=int))
        return Plan(t, traj, SolveStats("held", True, 1, 0.0, 0.0, 0.0), schedule)


PLANNER = PlannerSpec("stay", StaySettings, lambda system, settings, seed: Stay())
MPC = MPCSpec("hold", HoldSettings, lambda system, settings, margins: None,
              lambda system, settings, problem: Hold(system, settings))
'''


def test_a_toy_planner_and_mpc_kind_run_end_to_end(tmp_path):
    """Kinds registered by entry point, their settings subclassing the plug-in bases (the
    hooks hmpc calls have defaults): validated, checked, run, logged."""
    dist = write_dist(tmp_path / "toy", "hmpc-toy",
                      "[hmpc.planners]\nstay = hmpc_toy:PLANNER\n"
                      "[hmpc.mpcs]\nhold = hmpc_toy:MPC\n", {"hmpc_toy": TOY_KINDS})
    toy = tmp_path / "toy.toml"
    toy.write_text('name = "toy"\n[system]\nname = "ball"\n[sim]\nduration = 0.5\n'
                   '[planner]\nkind = "stay"\n[mpc]\nkind = "hold"\nrate_hz = 20\n')
    proc = hmpc(["run", str(toy), "--out", str(tmp_path / "run"), "-q"], dist, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["solves"] == 10 and summary["planner_calls"] == 1  # 20 Hz for 0.5 s
    solves = [m.data for m in read_log(tmp_path / "run" / "run.mcap").topic("/mpc/solve")]
    assert {s["status"] for s in solves} == {"held"}
    bad = hmpc(["run", str(toy), "--set", "mpc.u=5000", "--out", str(tmp_path / "bad")],
               dist, cwd=tmp_path)
    assert bad.returncode == 2 and "mpc.u: at most 1e3" in bad.stderr


def test_a_kind_whose_settings_skip_the_base_is_refused_by_name(tmp_path):
    text = TOY_KINDS.replace("class HoldSettings(MPCKindSettings):",
                             "class HoldSettings(BaseModel):").replace(
        "import numpy as np", "import numpy as np\nfrom pydantic import BaseModel")
    dist = write_dist(tmp_path / "toy", "hmpc-toy", "[hmpc.mpcs]\nhold = hmpc_toy:MPC\n",
                      {"hmpc_toy": text})
    toy = tmp_path / "toy.toml"
    toy.write_text('name = "toy"\n[system]\nname = "ball"\n[mpc]\nkind = "hold"\n')
    proc = hmpc(["run", str(toy), "--out", str(tmp_path / "run")], dist, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "must subclass hmpc_cli.plugin.MPCKindSettings" in proc.stderr


def test_a_plugin_registered_under_another_name_is_named_where_its_own_is_asked(tmp_path):
    """The dock's spec registered as 'dock2': a scenario naming 'dock' gets the entry point
    at fault, not 'unknown system'."""
    site = write_dist(tmp_path / "site", "hmpc-misnamed", "[hmpc.systems]\n"
                      "dock2 = hmpc_dock:SYSTEM\n",
                      {"hmpc_dock": (PLUGINS / "hmpc_dock.py").read_text()})
    scenario = tmp_path / "dock.toml"
    scenario.write_text('[system]\nname = "dock"\n')
    proc = hmpc(["run", str(scenario), "--out", str(tmp_path / "out"), "-q"], site,
                cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert error_lines(proc) == [
        f"error: {scenario}: system.name: entry point 'dock2' = 'hmpc_dock:SYSTEM' (group "
        "hmpc.systems) registers name 'dock': the entry point must be named after it"]


LOOSE = """
from dataclasses import dataclass, replace
from typing import Literal

from pydantic import BaseModel

from hmpc_dock import SYSTEM, DockParams


@dataclass
class PlainParams:
    name: str = "plain"


class LooseParams(BaseModel):  # no extra="forbid": a misspelled key would be ignored
    name: Literal["loose"] = "loose"


PLAIN = replace(SYSTEM, name="plain", params=PlainParams)
LOOSE = replace(SYSTEM, name="loose", params=LooseParams)
"""


def test_a_plugin_that_raises_shows_its_traceback_with_v(tmp_path):
    """The one error line; with -v, the plug-in's own traceback after it (where to look)."""
    site = _faulty_site(tmp_path)
    scenario = tmp_path / "badbuild.toml"
    scenario.write_text('[system]\nname = "badbuild"\n')
    proc = hmpc(["run", str(scenario), "--out", str(tmp_path / "out"), "-v"], site, PLUGINS,
                cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    lines = proc.stderr.splitlines()
    assert lines[0] == (f"error: {scenario}: system: 'badbuild' failed to build: ValueError: "
                        "dock_at must lie inside the track")
    assert lines[1] == "Traceback (most recent call last):"
    assert any("hmpc_faulty.py" in line and "in _fail" in line for line in lines)
    assert lines[-1] == "ValueError: dock_at must lie inside the track"
    assert not (tmp_path / "out").exists()


def test_parameters_that_are_not_a_strict_pydantic_model_refuse_that_plugin_only(tmp_path):
    """A dataclass as parameters, or a pydantic model that lets unknown keys through: that
    entry point is refused by name (exit 2, nothing written); the other systems run."""
    site = write_dist(tmp_path / "site", "hmpc-loose", "[hmpc.systems]\n"
                      "plain = hmpc_loose:PLAIN\nloose = hmpc_loose:LOOSE\n",
                      {"hmpc_loose": LOOSE})
    where = "entry point {0!r} = 'hmpc_loose:{1}' (group hmpc.systems): its parameters {2!r}"
    for name, spec, model, reason in [
            ("plain", "PLAIN", "PlainParams", "must be a pydantic model (a subclass of "
                                              "pydantic.BaseModel)"),
            ("loose", "LOOSE", "LooseParams", "must forbid unknown keys, or a misspelled key "
                                              "in a scenario is silently ignored: set "
                                              'model_config = ConfigDict(extra="forbid")')]:
        scenario = tmp_path / f"{name}.toml"
        scenario.write_text(f'[system]\nname = "{name}"\n')
        proc = hmpc(["run", str(scenario), "--out", str(tmp_path / name), "-q"], site,
                    PLUGINS, cwd=tmp_path)
        assert proc.returncode == 2, proc.stderr[-3000:]
        assert error_lines(proc) == [f"error: {scenario}: system.name: "
                                     f"{where.format(name, spec, model)} {reason}"]
        assert not (tmp_path / name).exists()
    schema = hmpc(["schema"], site, PLUGINS, cwd=tmp_path)
    assert schema.returncode == 0, schema.stderr[-3000:]
    assert {"ball", "biped", "dock"} <= set(json.loads(schema.stdout)["properties"]["system"][
        "discriminator"]["mapping"])




_DOCK_TEXT = (PLUGINS / "hmpc_dock.py").read_text()
#: (case, entry points, module text, scenario, the one error line after "error: {scenario}: ")
_AUTHOR_MISTAKES = [
    ("name typed str", "[hmpc.systems]\ndock = hmpc_dock:SYSTEM\n",
     _DOCK_TEXT.replace('name: Literal["dock"] = "dock"', 'name: str = "dock"'),
     '[system]\nname = "dock"\n',
     "system.name: entry point 'dock' = 'hmpc_dock:SYSTEM' (group hmpc.systems): "
     "DockParams.name must be Literal['dock'] = 'dock', not str (a scenario's [system] "
     "section is told apart by it)"),
    ("kind typed str", "[hmpc.planners]\nstay = hmpc_toy:PLANNER\n",
     TOY_KINDS.replace('kind: Literal["stay"] = "stay"', 'kind: str = "stay"'),
     '[system]\nname = "ball"\n[planner]\nkind = "stay"\n',
     "planner: entry point 'stay' = 'hmpc_toy:PLANNER' (group hmpc.planners): "
     "StaySettings.kind must be Literal['stay'] = 'stay', not str (a scenario's [planner] "
     "section is told apart by it)"),
    ("no rate_hz", "[hmpc.mpcs]\nhold = hmpc_toy:MPC\n",
     TOY_KINDS.replace("    rate_hz: int = 10\n", ""),
     '[system]\nname = "ball"\n[mpc]\nkind = "hold"\n',
     "mpc: entry point 'hold' = 'hmpc_toy:MPC' (group hmpc.mpcs): HoldSettings needs a "
     "field rate_hz (the re-solve rate [Hz] the loop keeps), e.g. rate_hz: int = 10"),
    ("a bundled kind's name", "[hmpc.planners]\ncem = hmpc_toy:PLANNER\n",
     TOY_KINDS.replace('"stay"', '"cem"'), '[system]\nname = "ball"\n',
     "planner 'cem', the default of system 'ball', cannot be used: kind 'cem' is registered "
     "twice in group hmpc.planners: 'hmpc_cli.planner.cem:PLANNER' and 'hmpc_toy:PLANNER'"),
    ("misnamed planner", "[hmpc.planners]\nstayer = hmpc_toy:PLANNER\n", TOY_KINDS,
     '[system]\nname = "ball"\n[planner]\nkind = "stay"\n',
     "planner: entry point 'stayer' = 'hmpc_toy:PLANNER' (group hmpc.planners) registers "
     "kind 'stay': the entry point must be named after it"),
    ("misspelled initial mode", "[hmpc.systems]\ndock = hmpc_dock:SYSTEM\n",
     _DOCK_TEXT.replace('initial_mode="free"', 'initial_mode="fre"'),
     '[system]\nname = "dock"\n',
     "system: 'dock' failed to build: ValueError: dock: initial_mode 'fre' is not a mode "
     "(modes: 'free', 'docked'; did you mean 'free'?)"),
    ("flow not finite at x0", "[hmpc.systems]\ndock = hmpc_dock:SYSTEM\n",
     _DOCK_TEXT.replace("ca.vertcat(vel, u / p.mass + w)",
                        "ca.vertcat(vel, ca.sqrt(pos - 1.5) + u / p.mass + w)"),
     '[system]\nname = "dock"\n',
     "system.x0: the flow of mode 'free' is not finite at x0 (1, -4) with u = 0 and w = 0 "
     "(d/dt of v): the run would diverge at its first step; check the flow's expression "
     "where x0 lies, or move system.x0"),
    ("x0 set by the build", "[hmpc.systems]\ndock = hmpc_dock:SYSTEM\n",
     _DOCK_TEXT.replace("    x0: tuple[float, float] = (1.0, -4.0)", "    pass").replace(
         "x0=np.array(p.x0, dtype=float)", "x0=np.array([-0.5, -4.0])"),
     '[system]\nname = "dock"\n',
     "the x0 that 'dock' builds (it has no x0 setting): (-0.5, -4) lies past guard 'bumper' "
     "of its initial mode 'free' (gap -0.5 < 0), so the run would start outside that "
     "mode's domain; move x0 or the guard"),
]


@pytest.mark.parametrize("case, entry_points, text, scenario, line", _AUTHOR_MISTAKES,
                         ids=[m[0] for m in _AUTHOR_MISTAKES])
def test_a_plugin_authors_mistake_is_one_line_naming_it(tmp_path, case, entry_points, text,
                                                        scenario, line):
    """Mistakes a review made writing plug-ins from plugins.md: a name or kind typed str
    broke every scenario (exit 1, PydanticUserError), an MPC without rate_hz and a planner
    under a bundled kind's name crashed (AttributeError, KeyError), a misnamed planner was
    'unknown kind', a misspelled initial mode named no choice, a flow NaN at x0 ran and
    'diverged'. Each is now one exit-2 line, nothing written."""
    module = "hmpc_dock" if "hmpc_dock" in entry_points else "hmpc_toy"
    site = write_dist(tmp_path / "site", "hmpc-mistake", entry_points, {module: text})
    path = tmp_path / "s.toml"
    path.write_text(scenario)
    proc = hmpc(["run", str(path), "--out", str(tmp_path / "out"), "-q"], site, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert error_lines(proc) == [f"error: {path}: {line}"]
    assert not (tmp_path / "out").exists()


def test_a_plugin_that_raises_on_import_shows_its_traceback_with_v(tmp_path):
    """-v showed the traceback of a plug-in whose build raises, not of one whose module
    raises while imported: now both, after the one error line."""
    site = write_dist(tmp_path / "site", "hmpc-boom", "[hmpc.systems]\nboom = hmpc_boom:SYSTEM\n",
                      {"hmpc_boom": "def _configure():\n    raise RuntimeError('bad config')\n\n"
                                    "_configure()\n"})
    scenario = tmp_path / "boom.toml"
    scenario.write_text('[system]\nname = "boom"\n')
    line = (f"error: {scenario}: system.name: entry point 'boom' = 'hmpc_boom:SYSTEM' (group "
            "hmpc.systems) failed to load: RuntimeError: bad config")
    quiet = hmpc(["run", str(scenario), "--out", str(tmp_path / "out")], site, cwd=tmp_path)
    assert quiet.returncode == 2 and error_lines(quiet) == [line], quiet.stderr[-3000:]
    loud = hmpc(["run", str(scenario), "--out", str(tmp_path / "out"), "-v"], site,
                cwd=tmp_path)
    lines = loud.stderr.splitlines()
    assert loud.returncode == 2 and lines[:2] == [line, "Traceback (most recent call last):"]
    assert any("hmpc_boom.py" in ln and "in _configure" in ln for ln in lines)
    assert lines[-1] == "RuntimeError: bad config" and not (tmp_path / "out").exists()


def test_a_flow_that_goes_non_finite_mid_run_names_the_states_and_the_mode(tmp_path):
    """A flow finite at x0 and NaN past it: the run ends diverged, its reason naming the
    non-finite states and the mode (it said only "non-finite or unbounded state")."""
    text = _DOCK_TEXT.replace("ca.vertcat(vel, u / p.mass + w)",
                              "ca.vertcat(vel, ca.sqrt(pos - 0.9) + u / p.mass + w)")
    site = write_dist(tmp_path / "site", "hmpc-nan", "[hmpc.systems]\ndock = hmpc_dock:SYSTEM\n",
                      {"hmpc_dock": text})
    path = tmp_path / "s.toml"
    path.write_text('[system]\nname = "dock"\n')
    proc = hmpc(["run", str(path), "--out", str(tmp_path / "out"), "-q"], site, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]  # it ran (1 with --strict)
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["diverged"] is True and not summary["success"]
    assert summary["reason"] == "diverged: non-finite state (p = nan, v = nan) in mode 'free'"
