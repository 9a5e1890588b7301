"""House rules: packages import downward only (one table), no import cycle at all, peers never
import each other, nothing imports a system plug-in, no system-name dispatch, one class per
name."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "hmpc_cli"

#: package (first part under hmpc_cli; "plugin", "lowlevel" are modules) -> what it may import.
#: Floors, bottom up: core -> systems, sim, mpc, lowlevel, tube, log -> planner, run -> sweep
#: -> analysis -> figures -> report -> cli. hmpc_cli/__init__ (the version) is open to all.
BELOW_RUN = {"core", "sim", "lowlevel", "mpc", "tube", "log"}
ALLOWED: dict[str, set[str]] = {
    "core": set(),
    "systems": {"core", "plugin"},
    "sim": {"core"},
    "lowlevel": {"core"},
    "mpc": {"core"},
    "tube": {"core"},
    "log": {"core"},
    "planner": {"core", "sim"},
    "run": {"core", *BELOW_RUN, "planner"},
    "sweep": {"core", "log", "run"},
    "analysis": {"core", "log", "run", "tube", "sweep"},
    "figures": {"core", "log", "analysis"},
    "report": {"core", "log", "run", "tube", "sweep", "analysis", "figures"},
    "cli": {"core", *BELOW_RUN, "planner", "run", "sweep", "analysis", "figures", "report"},
    "plugin": {"core"},
    "__main__": {"cli"},
}
#: the peers of the stack contract: planner, fixed-mode MPC, low level, tube and run log
PEERS = {"planner", "mpc", "lowlevel", "tube", "log"}
SYSTEM_NAMES = {"ball", "biped"}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in PKG.rglob("*.py")}


def _resolve(module: str, name: str | None) -> str:
    """``from module import name``: the module ``name`` when it is one, else ``module``."""
    if name and f"{module}.{name}" in MODULES:
        return f"{module}.{name}"
    return module


def imports_of(path: Path) -> set[str]:
    """Every hmpc_cli module ``path`` imports: top level, in functions, under TYPE_CHECKING."""
    me = module_name(path)
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = me.split(".")[: len(me.split(".")) - node.level
                                    + (1 if path.name == "__init__.py" else 0)]
                base = ".".join(parts + ([node.module] if node.module else []))
            if base == "hmpc_cli" or base.startswith("hmpc_cli."):
                out |= {_resolve(base, a.name) for a in node.names}
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("hmpc_cli")}
    return out - {me}


def package_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "hmpc_cli"


GRAPH = {m: imports_of(p) for m, p in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10_000)
    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_anywhere_in_the_package():
    """Function-level and TYPE_CHECKING imports count: a cycle is a cycle."""
    assert _cycles(GRAPH) == []


def test_every_import_resolves_to_a_module_of_the_package():
    for m, targets in GRAPH.items():
        unknown = targets - set(MODULES)
        assert not unknown, f"{m} imports {unknown}, which are not hmpc_cli modules"


def test_the_table_names_every_package_and_every_package_says_what_it_may_import():
    tops = {package_of(m) for m in MODULES} - {"hmpc_cli"}
    assert tops - {"systems"} <= set(ALLOWED), tops - set(ALLOWED)
    for name in tops:
        init = PKG / name / "__init__.py"
        if init.is_file() and name not in {"systems", "figures", "tube"}:
            doc = ast.get_docstring(ast.parse(init.read_text())) or ""
            assert "May import:" in doc, f"{init.relative_to(ROOT)}: say what it may import"


def test_packages_import_only_what_the_table_allows():
    for m, targets in GRAPH.items():
        me = package_of(m)
        if me == "hmpc_cli":
            # only the BLAS pin, which must run before NumPy loads: stdlib only
            assert targets <= {"hmpc_cli.core.blas"}, f"hmpc_cli/__init__ imports {targets}"
            assert not GRAPH.get("hmpc_cli.core.blas"), GRAPH.get("hmpc_cli.core.blas")
            continue
        allowed = ALLOWED[me] | {me, "hmpc_cli"}
        bad = {t for t in targets if package_of(t) not in allowed}
        assert not bad, f"{m} ({me}) imports {bad}; {me} may import {sorted(ALLOWED[me])}"


def test_peers_do_not_import_each_other():
    for m, targets in GRAPH.items():
        me = package_of(m)
        if me in PEERS:
            bad = {package_of(t) for t in targets} & PEERS - {me}
            assert not bad, f"{m} imports peer package(s) {bad}"


def test_nothing_imports_a_system_plugin():
    """Systems come through the registry's entry points, never by import."""
    for m, targets in GRAPH.items():
        if package_of(m) != "systems":
            bad = {t for t in targets if package_of(t) == "systems"}
            assert not bad, f"{m} imports system plug-in(s) {bad}"


def test_nothing_below_run_reads_a_scenario():
    for m, targets in GRAPH.items():
        if package_of(m) in BELOW_RUN | {"systems", "planner"}:
            assert "hmpc_cli.run.scenario" not in targets, m


def test_the_top_level_holds_packages_and_four_modules():
    modules = sorted(p.name for p in PKG.glob("*.py"))
    assert modules == ["__init__.py", "__main__.py", "lowlevel.py", "plugin.py"], modules


def test_help_does_not_import_heavy_modules():
    code = ("import sys; from hmpc_cli.cli import app; "
            "print(sorted(m for m in ('casadi', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    assert json.loads(out.replace("'", '"')) == []


def test_bundled_schema_file_is_current():
    from hmpc_cli.run.schema import scenario_json_schema

    bundled = json.loads((ROOT / "scenarios" / "scenario.schema.json").read_text())
    assert bundled == scenario_json_schema(), \
        "regenerate: hmpc schema > scenarios/scenario.schema.json"


def _compares_a_system_name(node: ast.AST) -> bool:
    """``x == "ball"``, ``"biped" in ...``: any comparison with a bundled system's name."""
    if isinstance(node, ast.Compare):
        parts = [node.left, *node.comparators]
        return any(isinstance(p, ast.Constant) and p.value in SYSTEM_NAMES for p in parts)
    return False


def test_no_code_outside_systems_tests_a_system_name():
    for m, path in MODULES.items():
        if package_of(m) == "systems":
            continue
        tree = ast.parse(path.read_text())
        bad = [n.lineno for n in ast.walk(tree) if _compares_a_system_name(n)]
        assert not bad, f"{path.relative_to(ROOT)}:{bad} compares with a system name"


def test_no_two_classes_share_a_name():
    """Every class in the package, private and nested ones included, has a name of its own."""
    where: dict[str, list[str]] = {}
    for m, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                where.setdefault(node.name, []).append(f"{m}:{node.lineno}")
    shared = {name: places for name, places in sorted(where.items()) if len(places) > 1}
    assert not shared, f"classes sharing a name: {shared}"


def test_figures_read_logs_only_and_never_rebuild_a_model():
    """Figures draw what the run log or a computed result hands them."""
    for m, path in MODULES.items():
        if package_of(m) == "figures":
            bad = {t for t in GRAPH[m] if t in {"hmpc_cli.core.registry", "hmpc_cli.log.recorder"}}
            assert not bad, f"{path.relative_to(ROOT)} imports {bad}"
            assert "build_system" not in path.read_text(), path


def test_the_plugin_api_exports_exactly_what_it_imports():
    import hmpc_cli.plugin as api

    tree = ast.parse((PKG / "plugin.py").read_text())
    imported = {a.asname or a.name for n in tree.body if isinstance(n, ast.ImportFrom)
                and n.module != "__future__" for a in n.names}
    assert set(api.__all__) == imported
    assert all(hasattr(api, name) for name in api.__all__)


def _plugin_imports(text: str) -> set[str]:
    """hmpc_cli modules imported by a piece of Python source."""
    out = set()
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("hmpc_cli"):
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("hmpc_cli")}
    return out


def test_plugins_and_the_docs_plugin_examples_import_only_the_plugin_api():
    sources = {p: p.read_text() for p in (ROOT / "tests" / "plugins").rglob("*.py")}
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        blocks = doc.read_text().split("```python")[1:]
        for k, block in enumerate(blocks):
            sources[Path(f"{doc.name} python block {k + 1}")] = block.split("```")[0]
    assert sources
    for where, text in sources.items():
        bad = _plugin_imports(text) - {"hmpc_cli.plugin"}
        assert not bad, f"{where} imports {bad}: a plug-in imports hmpc_cli.plugin only"
