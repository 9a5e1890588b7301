"""Integrity: the compiled rollout cache, damaged logs in figures, strict JSON, Dask connect."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path

import pytest

from conftest import BALL, REPO, cli_env, hmpc_command

HAVE_CC = bool(shutil.which("cc") or shutil.which("gcc"))
needs_cc = pytest.mark.skipif(not HAVE_CC, reason="no C compiler on this machine")

# a stand-in for the generated rollout source: the ABI entry points plus a marker
TINY = """
#define E __attribute__((visibility("default")))
E int hm_abi(void) { return 4; }
E int hm_rollout(void) { return 0; }
E int hm_step(void) { return 0; }
E int hm_trajectory(void) { return 0; }
E int hm_marker(void) { return MARK; }
"""
BUILD = ("import sys; from hmpc_cli.sim import rollout as rc; "
         "lib, path, s = rc.build_library(open(sys.argv[1]).read()); "
         "print(path, s is not None, lib.hm_marker())")


def _strict(text: str):
    def no_constant(c):
        raise ValueError(f"non-standard JSON constant {c}")

    return json.loads(text, parse_constant=no_constant)


def _build(src: Path, cache: Path, **env) -> tuple[Path, bool, int, str]:
    """build_library in a fresh process: (library path, compiled?, marker, stderr)."""
    proc = subprocess.run([sys.executable, "-c", BUILD, str(src)], capture_output=True,
                          text=True, timeout=60, cwd=REPO,
                          env={**os.environ, "HMPC_CACHE_DIR": str(cache), **env})
    assert proc.returncode == 0, proc.stderr[-2000:]
    path, compiled, marker = proc.stdout.split()
    return Path(path), compiled == "True", int(marker), proc.stderr


@pytest.fixture
def tiny_source(tmp_path):
    src = tmp_path / "tiny.c"
    src.write_text(TINY.replace("MARK", "1"))
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    return src, cache


@needs_cc
def test_truncated_library_is_rebuilt_not_loaded(tiny_source):
    src, cache = tiny_source
    path, compiled, marker, _ = _build(src, cache)
    assert compiled and marker == 1 and path.parent == cache
    assert (cache / (path.name + ".sha256")).read_text().split()[0] != ""
    with open(path, "r+b") as f:  # a build cut short (disk full, killed copy)
        f.truncate(path.stat().st_size // 3)
    again, compiled, marker, _ = _build(src, cache)
    assert again == path and compiled and marker == 1  # rebuilt, no SIGBUS
    assert _build(src, cache)[1] is False  # verified copy: no rebuild


@needs_cc
def test_planted_library_is_refused_and_rebuilt(tiny_source, tmp_path):
    src, cache = tiny_source
    path, _, _, _ = _build(src, cache)
    other = tmp_path / "other.c"
    other.write_text(TINY.replace("MARK", "666"))
    planted = tmp_path / "planted.so"
    subprocess.run(["cc", "-shared", "-fPIC", "-o", str(planted), str(other)], check=True)
    shutil.copy(planted, path)  # a valid library of someone else's under the expected name
    again, compiled, marker, _ = _build(src, cache)
    assert again == path and compiled and marker == 1


@needs_cc
def test_group_or_world_writable_cache_is_not_used(tiny_source):
    src, cache = tiny_source
    cache.chmod(0o777)
    path, compiled, marker, err = _build(src, cache)
    assert path.parent != cache and compiled and marker == 1
    assert "is not used" in err and "writable by group or others" in err
    assert list(cache.iterdir()) == []


@needs_cc
def test_compiler_identity_is_part_of_the_key(tiny_source, tmp_path):
    src, cache = tiny_source
    paths = []
    for name, version in (("cc1", "one 1.0"), ("cc2", "two 2.0")):
        wrapper = tmp_path / name
        wrapper.write_text(f'#!/bin/sh\n[ "$1" = --version ] && echo "{version}" && exit 0\n'
                           f'exec cc "$@"\n')
        wrapper.chmod(0o755)
        paths.append(_build(src, cache, CC=str(wrapper))[0])
    assert paths[0] != paths[1]


@needs_cc
def test_ball_rollout_survives_a_truncated_cache(tmp_path):
    code = ("import numpy as np; from hmpc_cli.sim.rollout import CRollout; "
            "from hmpc_cli.systems.ball import BallParams, build_ball; "
            "b = build_ball(BallParams(radius=0.13)); c = CRollout(b); "
            "cost, _ = c.cost(np.asarray(b.x0, float), 0, np.zeros((3, 5, 2)), 0.05, 1, 1e3, "
            "1e4); print(c.path, c.compile_seconds is not None, np.isfinite(cost).all())")
    env = {**os.environ, "HMPC_CACHE_DIR": str(tmp_path / "cache")}

    def run():
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=120, env=env, cwd=REPO)
        assert proc.returncode == 0, proc.stderr[-2000:]  # -7 would be SIGBUS
        return proc.stdout.split()

    path, compiled, finite = run()
    assert compiled == "True" and finite == "True"
    with open(path, "r+b") as f:
        f.truncate(4096)
    assert run() == [path, "True", "True"]


@pytest.mark.slow
@needs_cc
def test_failed_c_build_is_a_planner_error_not_an_mpc_one(tmp_path):
    env = {**cli_env(), "CC": "false", "HMPC_CACHE_DIR": str(tmp_path / "cache")}
    proc = subprocess.run([*hmpc_command(), "run", str(BALL), "--set",
                           "planner.rollout_backend=c", "--out", str(tmp_path / "r"), "-q"],
                          capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "planner.rollout_backend = 'c'" in proc.stderr
    assert "mpc:" not in proc.stderr and "Traceback" not in proc.stderr
    auto = subprocess.run([*hmpc_command(), "run", str(BALL), "--set", "sim.duration=0.1",
                           "--out", str(tmp_path / "a"), "-q"],
                          capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert auto.returncode == 0, auto.stderr
    assert "warning: C rollouts unavailable, using NumPy" in auto.stderr


# ---- damaged logs in figures --------------------------------------------------------------

TINY_SWEEP = """name = "tiny"
scenario = "{ball}"
seeds = [0]
[set]
"sim.duration" = 1.5
"planner.iterations" = 4
"planner.samples" = 10
"planner.knots" = 10
"mpc.horizon" = 1.0
[grid]
controller = [{{ label = "10 Hz fixed", "mpc.rate_hz" = 10 }}]
disturbance = [
  {{ label = "nominal", "disturbance.kind" = "none" }},
  {{ label = "trial 1", "disturbance.kind" = "paper_fig3", "disturbance.trial" = 1 }},
  {{ label = "trial 2", "disturbance.kind" = "paper_fig3", "disturbance.trial" = 2 }},
]
"""


@pytest.fixture(scope="module")
def sweep_dir(tmp_path_factory):
    base = tmp_path_factory.mktemp("sweep")
    (base / "tiny.toml").write_text(TINY_SWEEP.format(ball=BALL.as_posix()))
    proc = subprocess.run([*hmpc_command(), "sweep", "tiny.toml", "--workers", "1", "--out",
                           "out"], capture_output=True, text=True, timeout=120,
                          env=cli_env(), cwd=base)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return base / "out"


def _logs(table: Path) -> dict[str, Path]:
    with open(table / "results.csv") as f:
        return {r["disturbance"]: table / r["log"] for r in csv.DictReader(f)}


def _chunks(path: Path):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return sorted(make_reader(f).get_summary().chunk_indexes,
                      key=lambda c: c.chunk_start_offset)


def _damage(sweep_dir: Path, tmp_path: Path) -> tuple[Path, Path, Path]:
    """A copy with trial 1 bit-flipped in its last chunk and trial 2 cut to 200 bytes.

    (The first chunk holds /run/info alone: the run flushes it at once.)
    """
    table = tmp_path / "sweep"
    shutil.copytree(sweep_dir, table)
    logs = _logs(table)
    flipped, cut = logs["trial 1"], logs["trial 2"]
    chunks = _chunks(flipped)
    assert len(chunks) >= 3
    data = bytearray(flipped.read_bytes())
    at = chunks[-1].chunk_start_offset + chunks[-1].chunk_length // 2
    for k in range(8):
        data[at + 97 * k] ^= 0x55
    flipped.write_bytes(bytes(data))
    with open(cut, "r+b") as f:
        f.truncate(200)
    return table, flipped, cut


def test_read_log_stops_at_a_bit_flip(sweep_dir, tmp_path):
    from hmpc_cli.log.reader import read_log
    from hmpc_cli.log.rundata import read_run

    _, flipped, _ = _damage(sweep_dir, tmp_path)
    log = read_log(flipped)
    assert not log.complete and log.damage
    run = read_run(flipped)
    assert run.damage and len(run.t) > 0


def test_fig3_skips_unreadable_logs_and_notes_damaged_ones(sweep_dir, tmp_path):
    table, flipped, cut = _damage(sweep_dir, tmp_path)
    proc = subprocess.run([*hmpc_command(), "plot", "fig3", str(table), "--formats", "png"],
                          capture_output=True, text=True, timeout=120, env=cli_env(),
                          cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    warnings = [w for w in proc.stderr.splitlines() if w.startswith("warning:")]
    assert any(str(cut) in w and "skipped" in w for w in warnings), proc.stderr
    assert any(str(flipped) in w and "damaged" in w for w in warnings), proc.stderr
    assert (table / "fig3.png").stat().st_size > 0
    with open(table / "fig3_counts.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert row["runs"] == "2"


def test_report_page_names_the_skipped_logs(sweep_dir, tmp_path):
    from hmpc_cli.report.page import ReportInputs, write_report

    table, flipped, cut = _damage(sweep_dir, tmp_path)
    from hmpc_cli.report.paths import portable_path

    page = write_report(tmp_path / "results", ReportInputs(table, None, None, None), "t")
    text = page.read_text()
    # named as the page names paths outside the repository: no machine's absolute path
    assert portable_path(cut) in text and portable_path(flipped) in text and "damaged" in text
    assert str(tmp_path) not in text


def test_fig3_with_every_log_unreadable_is_a_clear_error(sweep_dir, tmp_path):
    table = tmp_path / "sweep"
    shutil.copytree(sweep_dir, table)
    for log in _logs(table).values():
        log.write_bytes(log.read_bytes()[:100])
    proc = subprocess.run([*hmpc_command(), "plot", "fig3", str(table), "--formats", "png"],
                          capture_output=True, text=True, timeout=120, env=cli_env(),
                          cwd=tmp_path)
    assert proc.returncode == 2 and "no readable run log" in proc.stderr
    assert "Traceback" not in proc.stderr


# ---- strict JSON ---------------------------------------------------------------------------

def test_json_writer_turns_non_finite_into_null():
    import numpy as np

    from hmpc_cli.core.jsonio import dumps
    from hmpc_cli.run.runner import jsonable

    value = {"final_error": math.inf, "t": -math.inf, "m": math.nan,
             "a": [1.0, np.float64("inf"), np.float32(2.5)], "arr": np.array([np.nan, 1.0])}
    assert _strict(dumps(value)) == {"final_error": None, "t": None, "m": None,
                                     "a": [1.0, None, 2.5], "arr": [None, 1.0]}
    assert _strict(json.dumps(jsonable(value), allow_nan=False))["final_error"] is None


def test_summaries_of_real_runs_are_strict_json(sweep_dir):
    for summary in sweep_dir.glob("runs/*/summary.json"):
        data = _strict(summary.read_text())
        assert data["solve_time_median"] is None or math.isfinite(data["solve_time_median"])


def test_every_json_file_writer_is_strict():
    """Files hmpc writes go through allow_nan=False (jsonio.dumps or an explicit flag)."""
    pattern = re.compile(r"write_text\(\s*json\.dumps\((?![^\n]*allow_nan=False)")
    for path in (REPO / "hmpc_cli").rglob("*.py"):
        text = path.read_text()
        assert not pattern.search(text), f"{path}: JSON file written without allow_nan=False"
        assert "json.dump(" not in text, f"{path}: json.dump to a file"


# ---- Dask connect deadline -------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_dask_silent_peer_fails_fast_with_a_hint():
    from hmpc_cli.cli.sweep import connect_dask
    from hmpc_cli.run.scenario import ScenarioError

    pytest.importorskip("distributed")
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen(4)  # accepts (in the kernel) and never says a word
        address = f"tcp://127.0.0.1:{server.getsockname()[1]}"
        start = time.monotonic()
        with pytest.raises(ScenarioError) as err:
            connect_dask(address, 2.0)
    assert time.monotonic() - start < 60  # a hang guard (the deadline is 2 s), not a timing
    (line,) = err.value.lines
    assert line.startswith(f"--dask {address}: no Dask scheduler answered within 2 s")
    assert "8787" in line and "8786" in line


class _Quiet(BaseHTTPRequestHandler):
    def do_GET(self):
        self.send_response(200)
        self.end_headers()
        self.wfile.write(b"dashboard")

    def log_message(self, *args):
        pass


@pytest.mark.slow
def test_dask_http_port_exits_2_quickly(tmp_path):
    pytest.importorskip("distributed")
    (tmp_path / "tiny.toml").write_text(TINY_SWEEP.format(ball=BALL.as_posix()))
    server = HTTPServer(("127.0.0.1", 0), _Quiet)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    address = f"tcp://127.0.0.1:{server.server_address[1]}"
    try:
        proc = subprocess.run([*hmpc_command(), "sweep", "tiny.toml", "--dask", address,
                               "--dask-timeout", "3", "--out", "out"], capture_output=True,
                              text=True, timeout=60, env=cli_env(), cwd=tmp_path)
    finally:
        server.shutdown()
        server.server_close()
    assert proc.returncode == 2, proc.stderr  # a hang fails through the timeout above
    assert f"error: --dask {address}: no Dask scheduler answered within 3 s" in proc.stderr
    assert "dashboard port 8787" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()
