"""Every command the README shows is run here (install and pytest are run by CI)."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest


ROOT = Path(__file__).resolve().parents[1]
RUN_BY_CI = {"pip install -e '.[test]'", "hmpc run scenarios/ball.toml"}


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```console\n(.*?)```", text, flags=re.S)
    return [line[2:].strip() for b in blocks for line in b.splitlines() if line.startswith("$ ")]


def test_readme_starts_with_the_two_commands():
    cmds = readme_commands()
    assert cmds[:2] == ["pip install -e '.[test]'", "hmpc run scenarios/ball.toml"]
    assert "`pytest`" in (ROOT / "README.md").read_text().split("##")[0]


@pytest.mark.slow
def test_readme_commands_run_in_order(tmp_path):
    for name in ("scenarios", "benchmarks", "sweeps"):
        os.symlink(ROOT / name, tmp_path / name)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for cmd in [c for c in readme_commands() if c not in RUN_BY_CI]:
        argv = shlex.split(cmd)
        if argv[0] == "hmpc":
            argv = [sys.executable, "-c", "from hmpc_cli.cli.app import main; main()"] + argv[1:]
        elif argv[0] == "python":
            argv[0] = sys.executable
        proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, env=env,
                              timeout=900)
        assert proc.returncode == 0, (cmd, proc.stderr[-3000:])
        assert proc.stdout.strip(), cmd
    assert (tmp_path / "fig3" / "fig3.pdf").is_file()
    page = (tmp_path / "results" / "README.md").read_text()
    assert "| 10 Hz fixed |" in page and (tmp_path / "results" / "report" / "fig3.png").is_file()
