"""The manual in docs/: complete, current (two pages generated from the code) and short README."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = ["index.md", "running.md", "log-format.md", "scenarios.md", "sweeps-and-report.md",
         "tubes.md", "biped.md", "plugins.md", "design-notes.md", "architecture.md",
         "performance.md"]


def _generator():
    spec = importlib.util.spec_from_file_location("docs_generate", DOCS / "generate.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_readme_is_at_most_200_lines():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 200, f"README.md has {len(lines)} lines; move text into docs/"


def test_readme_holds_no_measured_timings():
    text = (ROOT / "README.md").read_text()
    found = re.findall(r"\b\d+(?:\.\d+)?\s*(?:ms|s|min|minutes|seconds|hours?)\b", text)
    assert not found, f"measured timings in README.md: {found} (they belong in results/bench)"


def test_docs_has_every_page():
    missing = [p for p in PAGES if not (DOCS / p).is_file()]
    assert not missing, missing
    index = (DOCS / "index.md").read_text()
    assert all(f"({p})" in index for p in PAGES if p != "index.md")


def test_generated_pages_equal_the_generator_output():
    pages = _generator().generate()
    assert set(pages) == {"scenarios.md", "log-format.md"}
    for name, text in pages.items():
        assert (DOCS / name).read_text(encoding="utf-8") == text, (
            f"docs/{name} is out of date: run `python docs/generate.py`")


def test_generator_check_mode(tmp_path):
    proc = subprocess.run([sys.executable, str(DOCS / "generate.py"), "--check"],
                          capture_output=True, text=True, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr


def test_generated_pages_cover_the_models_and_topics():
    from hmpc_cli.log.topics import TOPICS
    from hmpc_cli.run.scenario import scenario_model

    scen = (DOCS / "scenarios.md").read_text()
    for key in ("system.circle_center", "system.circle_radius", "system.x0", "sim.rate_hz",
                "mpc.margins", "planner.kind", "lowlevel.kp"):
        assert f"`{key}`" in scen, key
    for section in scenario_model().model_fields:
        assert f"`{section}`" in scen or f"`[{section}]`" in scen, section
    log = (DOCS / "log-format.md").read_text()
    for topic, (name, _) in TOPICS.items():
        assert f"`{topic}`" in log and name in log, topic


def _modules() -> list[Path]:
    pkg = ROOT / "hmpc_cli"
    return sorted(p for p in pkg.rglob("*") if p.suffix in (".py", ".c")
                  and "__pycache__" not in p.parts)


def test_architecture_names_every_module():
    text = (DOCS / "architecture.md").read_text()
    missing = []
    for path in _modules():
        rel = path.relative_to(ROOT).as_posix()
        dotted = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        if rel not in text and f"`{dotted}`" not in text:
            missing.append(rel)
    assert not missing, f"docs/architecture.md does not name {missing}"


def _heading_anchors(path: Path) -> set[str]:
    """The anchors GitHub gives the headings of a Markdown file (outside code fences)."""
    anchors, seen, fenced = set(), {}, False
    for line in path.read_text().splitlines():
        if line.startswith("```"):
            fenced = not fenced
        m = None if fenced else re.match(r"#{1,6}\s+(.*)", line)
        if m is None:
            continue
        text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", m.group(1)).strip().lower()
        slug = re.sub(r"[^\w\- ]", "", text).replace(" ", "-")
        n = seen[slug] = seen.get(slug, -1) + 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


def test_docs_links_resolve():
    """Every relative link's file exists, and its #anchor is a heading of that file."""
    for doc in [ROOT / "README.md", ROOT / "results" / "README.md", *DOCS.glob("*.md")]:
        for target, anchor in re.findall(r"\]\(([^)#\s]*)(?:#([^)\s]*))?\)", doc.read_text()):
            if target.startswith("http"):
                continue
            if target.endswith("profile_switching.md"):
                continue  # written by the benchmark that profiles the switching NLP
            path = doc.parent / target if target else doc
            assert path.exists(), f"{doc.name}: broken link {target}"
            if anchor and path.suffix == ".md":
                assert anchor in _heading_anchors(path), \
                    f"{doc.name}: link {target}#{anchor}: no such heading in {path.name}"


def test_log_format_describes_every_field():
    """Every field row of docs/log-format.md's topic and detail tables says what it is."""
    rows = [m for line in (DOCS / "log-format.md").read_text().splitlines()
            if (m := re.fullmatch(r"\| `([^`]+)` \| ((?:array of |object)?[A-Za-z ]*) \| (.*) \|",
                                  line))]
    assert len(rows) > 150 and any(m[1] == "plan[:].<state>" for m in rows)
    empty = [m[1] for m in rows if not m[3].strip()]
    assert not empty, f"log-format.md: fields without a description: {empty}"


def test_the_sweep_file_example_plans(tmp_path):
    """scenarios.md's example sweep file is one hmpc plans (it set mpc.rate_hz on two
    axes and was refused), with the runs it describes."""
    from hmpc_cli.sweep.plan import plan_sweep

    text = (DOCS / "scenarios.md").read_text().split("Example (after `sweeps/fig3.toml`", 1)[1]
    example = text.split("```toml\n", 1)[1].split("```", 1)[0]
    (tmp_path / "sweeps").mkdir()
    (tmp_path / "scenarios").symlink_to(ROOT / "scenarios")
    (tmp_path / "sweeps" / "example.toml").write_text(example)
    plan = plan_sweep(tmp_path / "sweeps" / "example.toml")
    assert plan.spec.name == "fig3_example" and len(plan.runs) == 4  # 2 trials x 2 controllers
