"""House rules: layers import downward only; peers never import each other."""

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "hmpc_cli"
PEERS = {"planner", "mpc", "lowlevel", "recorder", "tube"}
BOTTOM = {"hybrid", "messages", "numeric"}


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
    from hmpc_cli.scenario import Scenario

    bundled = json.loads((ROOT / "scenarios" / "scenario.schema.json").read_text())
    assert bundled == Scenario.model_json_schema(), \
        "regenerate: hmpc schema > scenarios/scenario.schema.json"
