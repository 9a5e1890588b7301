"""Every command the README and the manual (docs/*.md) show in a ``console`` block is run here.

Each document's ``$ `` lines run in order in a fresh directory of their own (the scenarios,
benchmarks and sweeps linked in); install and the default run are run by CI (.ci/run:
the run verbatim, in a scratch directory). The
campaign-only commands (``CAMPAIGN_ONLY``) run apart, under ``pytest -m campaign``; in
their documents' order their committed results stand in for theirs.
"""

import csv
import os
import re
import shlex
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from conftest import assert_runs_match_the_committed_table


ROOT = Path(__file__).resolve().parents[1]
RUN_BY_CI = {"pip install -e '.[test]'", "hmpc run scenarios/ball.toml"}
#: documented commands CI's slow run leaves to ``pytest -m campaign`` (CI keeps within its
#: time), each with the committed results that stand in for its own where the document's
#: later commands read them: the two Figure 3 campaigns (about two minutes of both cores;
#: CI runs the hmpc-mode campaign's 10 Hz plan-once column against the committed table,
#: tests/test_claims.py), the benchmark suite's quick form (its machinery runs on short NLPs in
#: tests/test_bench_suite.py) and the targets benchmark's (its sections run on short runs
#: in tests/test_bench_targets.py)
CAMPAIGN_ONLY = {"hmpc sweep sweeps/fig3.toml --out repro/sweeps/fig3":
                 ("results/sweeps/fig3", "repro/sweeps/fig3"),
                 "hmpc sweep sweeps/fig3_reference.toml --out repro/sweeps/fig3_reference":
                 ("results/sweeps/fig3_reference", "repro/sweeps/fig3_reference"),
                 "python benchmarks/suite.py --quick": None,
                 "python benchmarks/bench_targets.py --runs 1 --no-campaign --out bench-quick":
                 None}
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def doc_commands(path: Path) -> list[str]:
    """The ``$ `` lines of every ```console block of a Markdown file, in order."""
    blocks = re.findall(r"```console\n(.*?)```", path.read_text(), flags=re.S)
    return [line[2:].strip() for b in blocks for line in b.splitlines() if line.startswith("$ ")]


def readme_commands() -> list[str]:
    return doc_commands(ROOT / "README.md")


def test_readme_starts_with_the_two_commands():
    cmds = readme_commands()
    assert cmds[:2] == ["pip install -e '.[test]'", "hmpc run scenarios/ball.toml"]
    assert "`pytest`" in (ROOT / "README.md").read_text().split("##")[0]


def test_console_blocks_hold_only_commands_the_runner_can_start():
    for doc in DOCUMENTS:
        for cmd in doc_commands(doc):
            if cmd in RUN_BY_CI:
                continue
            assert shlex.split(cmd)[0] in ("hmpc", "python"), (doc.name, cmd)


def test_the_campaign_only_commands_are_documented():
    assert set(CAMPAIGN_ONLY) <= {c for doc in DOCUMENTS for c in doc_commands(doc)}


def _run_commands(cmds: list[str], cwd: Path, campaign: bool = False) -> None:
    """Runs ``cmds`` in order in ``cwd``; the campaign-only ones only with ``campaign``."""
    for name in ("scenarios", "benchmarks", "sweeps"):
        os.symlink(ROOT / name, cwd / name)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for cmd in [c for c in cmds if c not in RUN_BY_CI]:
        if cmd in CAMPAIGN_ONLY and not campaign:
            if CAMPAIGN_ONLY[cmd]:
                committed, there = CAMPAIGN_ONLY[cmd]
                shutil.copytree(ROOT / committed, cwd / there)
            continue
        argv = shlex.split(cmd)
        if argv[0] == "hmpc":
            argv = [sys.executable, "-c", "from hmpc_cli.cli.app import main; main()"] + argv[1:]
        elif argv[0] == "python":
            argv[0] = sys.executable
        proc = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, env=env,
                              timeout=900)
        assert proc.returncode == 0, (cmd, proc.stderr[-3000:])
        assert proc.stdout.strip(), cmd


def _assert_the_committed_figure_3_table(cwd: Path, sweep: str, results: str = "results"
                                         ) -> None:
    """The campaign's table just made (in ``cwd/results``) gives the committed one run for
    run, hence the page's counts: 11/11 for every controller (the paper's 10 Hz plan-once
    9/11 is not reproduced)."""
    table = cwd / results / "sweeps" / sweep / "results.csv"
    assert assert_runs_match_the_committed_table(table, sweep) == 33
    with open(table, newline="") as f:
        held = Counter(r["controller"] for r in csv.DictReader(f) if r["success"] == "true")
    assert held == {"10 Hz fixed": 11, "20 Hz fixed": 11, "10 Hz replan": 11}, sweep


@pytest.mark.slow
def test_readme_commands_run_in_order(tmp_path):
    """The README's commands but the campaign-only ones (their committed results stand
    in): Figure 3's figure and the page are written from the campaign's table."""
    _run_commands(readme_commands(), tmp_path)
    assert (tmp_path / "repro" / "fig3" / "fig3.pdf").is_file()
    page = (tmp_path / "repro" / "README.md").read_text()
    assert "| 10 Hz fixed |" in page and (tmp_path / "repro" / "report" / "fig3.png").is_file()
    assert not (tmp_path / "results" / "README.md").exists()  # the committed page untouched


@pytest.mark.slow
@pytest.mark.campaign
def test_campaign_only_commands(tmp_path):
    """The documented commands CI leaves to the campaigns: each Figure 3 campaign gives
    the committed table; the quick forms of the benchmark suite and of the targets
    benchmark run."""
    assert list(CAMPAIGN_ONLY) == [
        "hmpc sweep sweeps/fig3.toml --out repro/sweeps/fig3",
        "hmpc sweep sweeps/fig3_reference.toml --out repro/sweeps/fig3_reference",
        "python benchmarks/suite.py --quick",
        "python benchmarks/bench_targets.py --runs 1 --no-campaign --out bench-quick"]
    _run_commands(list(CAMPAIGN_ONLY), tmp_path, campaign=True)
    for sweep in ("fig3", "fig3_reference"):
        _assert_the_committed_figure_3_table(tmp_path, sweep, "repro")


@pytest.mark.slow
@pytest.mark.parametrize("doc", [d for d in DOCUMENTS[1:] if doc_commands(d)],
                         ids=lambda d: d.name)
def test_docs_commands_run_in_order(doc, tmp_path):
    _run_commands(doc_commands(doc), tmp_path)
