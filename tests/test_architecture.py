"""House rules: layers import downward only; peers never import each other."""

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "hmpc_cli"
PEERS = {"planner", "mpc", "lowlevel", "recorder", "runlog", "tube"}
BOTTOM = {"hybrid", "messages", "numeric", "drawing"}
#: rooms that must work for any registered system: they never import a system plug-in
SYSTEM_AGNOSTIC = {"mpc", "planner", "figures", "loop", "plant", "runlog", "stack",
                   "scenario", "runner", "sweep", "report", "report_robustness", "lowlevel",
                   "sim", "tasks", "tube",
                   "scene", "drawing"}
SYSTEM_NAMES = {"ball", "biped"}


def imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hmpc_cli"):
            out.add(node.module.split(".")[1] if "." in node.module else "")
        elif isinstance(node, ast.Import):
            out |= {a.name.split(".")[1] for a in node.names if a.name.startswith("hmpc_cli.")}
    return out


def layer_of(path: Path) -> str:
    rel = path.relative_to(PKG)
    return rel.parts[0].removesuffix(".py")


def test_peers_do_not_import_each_other():
    for path in PKG.rglob("*.py"):
        me = layer_of(path)
        if me in PEERS:
            bad = (imports_of(path) & PEERS) - {me}
            assert not bad, f"{path.relative_to(ROOT)} imports peer layer(s) {bad}"


def test_bottom_layers_import_nothing_above_them():
    for path in PKG.rglob("*.py"):
        if layer_of(path) in BOTTOM:
            assert imports_of(path) <= BOTTOM, f"{path.relative_to(ROOT)} imports upward"


def test_modules_stay_small():
    for path in PKG.rglob("*.py"):
        assert len(path.read_text().splitlines()) <= 500, f"{path} is over 500 lines"


def test_help_does_not_import_heavy_modules():
    code = ("import sys; from hmpc_cli import cli; "
            "print(sorted(m for m in ('casadi', 'matplotlib') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True).stdout
    assert json.loads(out.replace("'", '"')) == []


def test_bundled_schema_file_is_current():
    from hmpc_cli.scenario import scenario_model

    bundled = json.loads((ROOT / "scenarios" / "scenario.schema.json").read_text())
    assert bundled == scenario_model().model_json_schema(), \
        "regenerate: hmpc schema > scenarios/scenario.schema.json"


def test_system_agnostic_rooms_import_no_system_plugin():
    for path in PKG.rglob("*.py"):
        if layer_of(path) in SYSTEM_AGNOSTIC:
            assert "systems" not in imports_of(path), \
                f"{path.relative_to(ROOT)} imports a system plug-in"


def _compares_a_system_name(node: ast.AST) -> bool:
    """``x == "ball"``, ``"biped" in ...``, ``match`` on a name: any comparison with a
    bundled system's name as a string constant."""
    if isinstance(node, ast.Compare):
        parts = [node.left, *node.comparators]
        return any(isinstance(p, ast.Constant) and p.value in SYSTEM_NAMES for p in parts)
    return False


def test_no_code_outside_systems_tests_a_system_name():
    for path in PKG.rglob("*.py"):
        if layer_of(path) == "systems":
            continue
        tree = ast.parse(path.read_text())
        bad = [n.lineno for n in ast.walk(tree) if _compares_a_system_name(n)]
        assert not bad, f"{path.relative_to(ROOT)}:{bad} compares with a system name"


def test_figures_read_logs_only_and_never_rebuild_a_model():
    """Figures draw what the run log (rundata) or a computed result hands them."""
    for path in (PKG / "figures").rglob("*.py"):
        bad = imports_of(path) & {"registry", "systems", "recorder"}  # types only from others
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"
        assert "build_system" not in path.read_text(), path
