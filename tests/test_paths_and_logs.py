"""Step 14, "nothing lies": output paths, sweep resume and ownership, damaged logs, counts, scene.

Table-driven: every writing command against every bad output path (exit 2, one error line,
nothing written); a sweep run is finished only with a complete log; damaged or foreign logs
are "damaged log" (exit 2), never an internal error; failed walking-MPC solves are counted;
the biped's plan and rollout lines break at resets. The fuzz and full-disk tests are slow.
"""

from __future__ import annotations

import errno
import json
import os
import random
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, mounted_tmpfs
from typer.testing import CliRunner

from hmpc_cli.cli.app import app

BALL = REPO / "scenarios" / "ball.toml"
BIPED = REPO / "scenarios" / "biped_stairs.toml"


def hmpc(args: list[str], cwd: Path | None = None):
    """``hmpc ARGS`` in this process (stderr apart), from ``cwd``."""
    old = Path.cwd()
    if cwd is not None:
        os.chdir(cwd)
    try:
        return CliRunner().invoke(app, [str(a) for a in args])
    finally:
        os.chdir(old)


def errors(res) -> list[str]:
    return [ln for ln in res.stderr.splitlines() if ln.strip()]


def listing(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def _short_run(tmp_path_factory, name: str, scenario, duration: float) -> Path:
    """A run of ``scenario`` cut to ``duration`` [s]; its directory."""
    out = tmp_path_factory.mktemp(name) / "run"
    res = hmpc(["run", scenario, "--set", f"sim.duration={duration}", "--out", out, "-q"])
    assert res.exit_code == 0, res.stderr
    return out


@pytest.fixture(scope="module")
def ball_run(tmp_path_factory) -> Path:
    return _short_run(tmp_path_factory, "ball", BALL, 0.3)


@pytest.fixture(scope="module")
def biped_run(tmp_path_factory) -> Path:
    return _short_run(tmp_path_factory, "biped", BIPED, 0.8)


# ----------------------------------------------------------------- output paths
def _sweep_file(d: Path, name: str = "tiny") -> Path:
    path = d / f"{name}.toml"
    path.write_text(f'name = "{name}"\nscenario = "{BALL}"\nseeds = [0]\n'
                    '[set]\n"sim.duration" = 0.05\n')
    return path


BAD = {  # name -> (the path, what the error line says)
    "empty": ("", "an empty path"),
    "file in the way": ("afile/sub", "cannot create it: afile is not a directory"),
    "proc": ("/proc/hmpc-out", "virtual file system"),
    "name too long": ("n" * 300, "name too long"),
    "dangling link": ("dangling/sub", "dangling symbolic link"),
    "link loop": ("loop/sub", "symbolic link loop"),
}
COMMANDS = {  # name -> args with the path as {P}, the check's kind
    "run --out": ["run", BALL, "--out", "{P}"],
    "sweep --out": ["sweep", "{SWEEP}", "--out", "{P}", "--workers", "1"],
    "plot --out": ["plot", "fig4", "{LOG}", "--out", "{P}"],
    "tube --write": ["tube", BALL, "--write", "{P}", "--samples", "10"],
    "tube --out": ["tube", BALL, "--out", "{P}", "--samples", "10"],
    "report --results": ["report", "--results", "{P}", "--biped", "", "--biped-push", "",
                         "--fig3-trials", "", "--realtime", ""],
    "replay --export": ["replay", "{LOG}", "--export", "{P}"],
    "replay --figures": ["replay", "{LOG}", "--figures", "{P}"],
}


@pytest.mark.parametrize("bad", list(BAD))
@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_writing_command_refuses_a_bad_output_path(tmp_path, ball_run, command, bad):
    (tmp_path / "afile").write_text("x")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    sweep = _sweep_file(tmp_path)
    before = listing(tmp_path)
    path, said = BAD[bad]
    args = [str(a).replace("{P}", path).replace("{SWEEP}", str(sweep))
            .replace("{LOG}", str(ball_run / "run.mcap")) for a in COMMANDS[command]]
    res = hmpc(args, tmp_path)
    assert res.exit_code == 2, (res.stdout, res.stderr)
    lines = errors(res)
    assert len(lines) == 1 and lines[0].startswith("error: ") and said in lines[0], lines
    assert "internal error" not in res.stderr and "Traceback" not in res.stderr
    assert listing(tmp_path) == before  # nothing written
    assert not (tmp_path / "results").exists()


@pytest.fixture
def readonly_dir(tmp_path):
    yield from mounted_tmpfs(tmp_path / "ro", "ro,size=64k", "a read-only directory")


@pytest.mark.parametrize("command", ["run --out", "sweep --out", "tube --write",
                                     "replay --export"])
def test_an_unwritable_directory_is_refused(tmp_path, readonly_dir, ball_run, command):
    args = [str(a).replace("{P}", str(readonly_dir / "x"))
            .replace("{SWEEP}", str(_sweep_file(tmp_path)))
            .replace("{LOG}", str(ball_run / "run.mcap")) for a in COMMANDS[command]]
    res = hmpc(args, tmp_path)
    assert res.exit_code == 2 and "read-only file system" in res.stderr, res.stderr
    assert len(errors(res)) == 1


def test_a_sweep_named_dotdot_never_writes_into_results(tmp_path):
    path = tmp_path / "up.toml"
    path.write_text(f'name = ".."\nscenario = "{BALL}"\n')
    res = hmpc(["sweep", path, "--workers", "1"], tmp_path)
    assert res.exit_code == 2 and "is not a name" in res.stderr, res.stderr
    assert listing(tmp_path) == ["up.toml"]


def test_two_runs_never_share_a_directory(tmp_path):
    from hmpc_cli.run.runner import RunDirTakenError, claim_run_dir, out_problem

    out = tmp_path / "x"
    assert out_problem(out) is None
    claim_run_dir(out)
    assert (out / "run.mcap").is_file()
    with pytest.raises(RunDirTakenError, match="already holds a run"):
        claim_run_dir(out)  # the second of two started at once
    assert "already holds a run" in out_problem(out)
    res = hmpc(["run", BALL, "--out", out], tmp_path)
    assert res.exit_code == 2 and "already holds a run" in res.stderr


# ----------------------------------------------------------------- atomic writes
def test_a_failed_write_leaves_no_temporary_and_claims_nothing(tmp_path, monkeypatch):
    from hmpc_cli.core.paths import atomic_file, write_atomic

    write_atomic(tmp_path / "a.txt", "old")
    with pytest.raises(OSError), atomic_file(tmp_path / "a.txt") as tmp:
        tmp.write_text("half")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert listing(tmp_path) == ["a.txt"] and (tmp_path / "a.txt").read_text() == "old"
    with pytest.raises(OSError), atomic_file(tmp_path / "b.txt") as tmp:
        tmp.write_bytes(b"")
        raise OSError(errno.ENOSPC, "No space left on device")
    assert listing(tmp_path) == ["a.txt"]  # no 0-byte temporary, no b.txt


def test_a_full_disk_while_saving_a_figure_keeps_nothing_half_written(tmp_path, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.figures.common import save_figure

    fig = plt.figure()

    def full(path, **_):
        Path(path).write_bytes(b"")
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(fig, "savefig", full)
    with pytest.raises(FigureInputError, match="No space left"):
        save_figure(fig, tmp_path, "f", ["png"])
    assert listing(tmp_path) == []


def test_a_full_disk_is_bad_environment_not_an_internal_error(tmp_path, ball_run,
                                                               monkeypatch):
    import hmpc_cli.analysis.export as export

    def full(path, rows):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(export, "_write_csv", full)
    res = hmpc(["replay", ball_run, "--export", tmp_path / "e", "-q"], tmp_path)
    assert res.exit_code == 2 and "No space left on device" in res.stderr, res.stderr
    assert "internal error" not in res.stderr
    assert listing(tmp_path / "e") == []  # no temporaries, no half tables


def test_an_export_that_fails_midway_leaves_the_directory_as_it_was(tmp_path, ball_run,
                                                                   monkeypatch):
    """A disk filling up at the third table: the new directory is gone, and an earlier
    export in it is left whole (7 tables and no info.json stayed, and the next export was
    refused; re-exported another log, the two were mixed)."""
    import hmpc_cli.analysis.export as export

    earlier = tmp_path / "e"
    assert hmpc(["replay", ball_run, "--export", earlier, "--topic", "summary", "-q"],
                tmp_path).exit_code == 0
    before = {p.name: p.read_bytes() for p in earlier.iterdir()}
    write, calls = export._write_csv, []

    def fills_up(path, rows):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        write(path, rows)

    monkeypatch.setattr(export, "_write_csv", fills_up)
    for out in (tmp_path / "new", earlier):
        calls.clear()
        res = hmpc(["replay", ball_run, "--export", out, "-q"], tmp_path)
        assert res.exit_code == 2 and "No space left on device" in res.stderr, res.stderr
        assert len(calls) == 3
    assert not (tmp_path / "new").exists()
    assert {p.name: p.read_bytes() for p in earlier.iterdir()} == before


def test_an_export_stopped_or_failed_leaves_nothing_and_a_stop_is_not_lost(
        tmp_path, ball_run, monkeypatch):
    """A stop signal while the staged files are moved in: the export completes, then the
    stop acts (exit 143; it was lost, exit 0). A failure that is not an OSError, deep in
    directories the export made: none of them is left (it left the directories). A dead
    export's staging directory is removed by the next export (it stayed for ever)."""
    import signal as sig

    import hmpc_cli.analysis.export as export

    out = tmp_path / "a" / "b" / "e"
    replace = Path.replace

    def stopped(self, target):
        if self.parent.name.startswith(".hmpc-export-") and not stopped.sent:
            stopped.sent = True
            os.kill(os.getpid(), sig.SIGTERM)
        return replace(self, target)

    stopped.sent = False
    monkeypatch.setattr(Path, "replace", stopped)
    res = hmpc(["replay", ball_run, "--export", out, "-q"], tmp_path)
    assert res.exit_code == 143, res.output
    assert (out / "info.json").is_file()  # moved in whole, then stopped
    monkeypatch.setattr(Path, "replace", replace)

    def broken(path, rows):
        raise UnicodeEncodeError("utf-8", "\ud800", 0, 1, "surrogates not allowed")

    monkeypatch.setattr(export, "_write_csv", broken)
    res = hmpc(["replay", ball_run, "--export", tmp_path / "x" / "y" / "e", "-q"], tmp_path)
    assert res.exit_code != 0 and not (tmp_path / "x").exists(), res.output
    monkeypatch.undo()
    dead = out / ".hmpc-export-999999999-abc"
    dead.mkdir()
    assert hmpc(["replay", ball_run, "--export", out, "-q"], tmp_path).exit_code == 0
    assert not dead.exists()


@pytest.fixture
def small_disk(tmp_path):
    yield from mounted_tmpfs(tmp_path / "disk", "size=200k", "a full disk")


@pytest.mark.slow
def test_a_sweep_on_a_full_disk_exits_2_and_says_what_was_kept(tmp_path, small_disk):
    path = tmp_path / "full.toml"
    path.write_text(f'name = "full"\nscenario = "{BALL}"\nseeds = [0, 1]\n')
    res = hmpc(["sweep", path, "--out", small_disk / "s", "--workers", "1"], tmp_path)
    assert res.exit_code == 2, (res.stdout, res.stderr)
    (line,) = errors(res)
    assert "No space left on device" in line and "of 2 runs kept" in line, line
    assert not [p for p in small_disk.rglob("*.tmp")]


@pytest.mark.slow
def test_a_plot_on_a_full_disk_exits_2_with_no_temporaries(tmp_path, small_disk, biped_run):
    (small_disk / "filler").write_bytes(b"\0" * 150_000)
    res = hmpc(["plot", "fig4", biped_run, "--out", small_disk / "p"], tmp_path)
    assert res.exit_code == 2 and "No space left" in res.stderr, res.stderr
    assert not [p for p in small_disk.rglob("*") if ".tmp" in p.name]


# ----------------------------------------------------------------- sweep resume / owner
def _damage(log: Path, how: str) -> None:
    if how == "missing":
        log.unlink()
    elif how == "empty":
        log.write_bytes(b"")
    elif how == "cut short":
        log.write_bytes(log.read_bytes()[: log.stat().st_size // 2])
    elif how == "no /run/summary":
        from mcap.writer import Writer

        with open(log, "wb") as f:
            w = Writer(f)
            w.start(profile="", library="test")
            w.register_channel("/run/info", "json", w.register_schema("I", "jsonschema", b"{}"))
            w.finish()


@pytest.mark.parametrize("how,finished", [("intact", True), ("missing", False),
                                          ("empty", False), ("cut short", False),
                                          ("no /run/summary", False)])
def test_a_sweep_run_is_finished_only_with_a_complete_log(tmp_path, ball_run, how, finished):
    from hmpc_cli.sweep.table import finished_in

    d = tmp_path / "r"
    shutil.copytree(ball_run, d)
    _damage(d / "run.mcap", how)
    toml = (d / "scenario.toml").read_text()
    assert (finished_in(d, toml) is not None) == finished


def test_resume_redoes_a_run_whose_log_is_gone(tmp_path):
    path = _sweep_file(tmp_path)
    out = tmp_path / "out"
    first = hmpc(["sweep", path, "--out", out, "--workers", "1"], tmp_path)
    assert first.exit_code == 0, first.stderr
    (run,) = (out / "runs").iterdir()
    (run / "run.mcap").unlink()  # summary.json stays: it must not be trusted alone
    again = hmpc(["sweep", path, "--out", out, "--workers", "1"], tmp_path)
    assert again.exit_code == 0, again.stderr
    assert "0 skipped (already done), 1 to run" in again.stdout
    assert (run / "run.mcap").stat().st_size > 0


@pytest.mark.parametrize("case,code,said", [
    ("another sweep", 2, "belongs to sweep 'other'"),
    ("not a sweep", 2, "is not a sweep's directory"),
    ("the same sweep", 0, ""), ("empty directory", 0, "")])
def test_a_sweep_directory_belongs_to_its_sweep(tmp_path, case, code, said):
    from hmpc_cli.sweep.lock import owner_problem

    out = tmp_path / "out"
    out.mkdir()
    if case == "another sweep":
        (out / "sweep.toml").write_text('name = "other"\n')
    elif case == "not a sweep":
        (out / "notes.txt").write_text("mine")
    elif case == "the same sweep":
        (out / "sweep.toml").write_text('name = "tiny"\n')
    problem = owner_problem(out, "tiny")
    assert (problem is None) == (code == 0) and said in (problem or "")
    if code:
        before = listing(tmp_path)
        res = hmpc(["sweep", _sweep_file(tmp_path), "--out", out], tmp_path)
        assert res.exit_code == 2 and said in res.stderr and len(errors(res)) == 1
        assert listing(tmp_path) == sorted([*before, "tiny.toml"])


# ----------------------------------------------------------------- damaged / foreign logs
def _foreign_log(path: Path, info: dict, extra: dict[str, list[dict]]) -> Path:
    """A valid MCAP with hmpc's topic names and wrongly typed fields."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="other")
        sid = w.register_schema("S", "jsonschema", b"{}")
        topics = {"/run/info": [info], **extra}
        for topic, msgs in topics.items():
            cid = w.register_channel(topic, "json", sid)
            for i, m in enumerate(msgs):
                w.add_message(cid, i * 1000, json.dumps(m).encode(), i * 1000)
        w.finish()
    return path


FOREIGN = {  # name -> (/run/info, other topics)
    "state x a string": ({"scenario_name": "x", "log_version": 3},
                         {"/sim/state": [{"t": 0.0, "x": "abc", "mode": 0}]}),
    "solve plan a number": ({"scenario_name": "x", "state_names": ["a"]},
                            {"/mpc/solve": [{"t": 0.0, "plan": 5, "success": True}]}),
    "info fields wrong": ({"scenario_name": "x", "versions": [1, 2], "seed": {},
                           "log_version": "three", "state_names": 7}, {}),
    "events of lists": ({"scenario_name": "x"}, {"/sim/event": [{"t": [1], "guard": "g"}],
                                                "/disturbance": [{"t": 0.0, "w": {"a": []}}]}),
}


_DAMAGE = "{log}: damaged log: its content cannot be read: "
FOREIGN_ERRORS = {  # (name, command) -> how its one error line starts (exit 2)
    **{(name, command): "error: " + ("--runs " if command == "tube --runs" else "")
       + _DAMAGE + kind
       for name, kind in (("state x a string", "ValueError"),
                          ("solve plan a number", "TypeError"),
                          ("info fields wrong", "TypeError"),
                          ("events of lists", "TypeError"))
       for command in ("plot fig2", "tube --runs")},
    ("state x a string", "plot fig4"): "error: {log}: cannot read log (" + _DAMAGE
                                        + "ValueError",
    ("info fields wrong", "plot fig4"): "error: {log}: cannot read log (" + _DAMAGE
                                         + "TypeError",
    ("events of lists", "plot fig4"): "error: {log}: cannot read log (" + _DAMAGE
                                       + "TypeError",
    ("solve plan a number", "plot fig4"): "error: {log}: not a walking run to draw (log "
                                          "version 1 has no geometry; re-run it with this hmpc)",
}
REPLAYED = {  # replay reads the messages as generic JSON: it checks each field's kind first
    "state x a string": "/sim/state at t = 0 s: x: expected an object, got a string",
    "solve plan a number": "/mpc/solve at t = 0 s: plan: expected an array, got a number",
    "info fields wrong": "/run/info at t = 0 s: seed: expected an integer, got an object",
    "events of lists": "/sim/event at t = 0 s: t: expected a number, got an array"}
FOREIGN_ERRORS.update({(name, command): "error: " + _DAMAGE + why
                       for name, why in REPLAYED.items()
                       for command in ("replay", "replay --export")})


@pytest.mark.parametrize("name", list(FOREIGN))
@pytest.mark.parametrize("command", ["replay", "replay --export", "plot fig4", "plot fig2",
                                     "tube --runs"])
def test_a_foreign_log_is_damage_not_an_internal_error(tmp_path, name, command):
    log = _foreign_log(tmp_path / "f.mcap", *FOREIGN[name])
    args = {"replay": ["replay", log], "replay --export": ["replay", log, "--export",
                                                           tmp_path / "e"],
            "plot fig4": ["plot", "fig4", log, "--out", tmp_path / "p"],
            "plot fig2": ["plot", "fig2", log, "--out", tmp_path / "p"],
            "tube --runs": ["tube", BALL, "--runs", log, "--samples", "10",
                            "--out", tmp_path / "t"]}[command]
    res = hmpc(args, tmp_path)
    assert "internal error" not in res.stderr and "Traceback" not in res.stderr
    assert res.exit_code == 2, (res.stdout, res.stderr)
    (line,) = errors(res)
    expected = FOREIGN_ERRORS[name, command].format(log=log)
    if command.startswith("replay"):  # the whole line: the field and its kind
        assert line == expected
    else:
        assert line.startswith(expected), line


def test_a_huge_length_field_is_damage_not_memory_error(tmp_path, biped_run):
    """A summary-section record whose length asks for exabytes (MemoryError) is damage."""
    from hmpc_cli.log.reader import read_log
    from hmpc_cli.log.rundata import read_run

    data = bytearray((biped_run / "run.mcap").read_bytes())
    footer = len(data) - 8 - 29  # opcode, length, summary_start, offset start, crc; magic
    (start,) = struct.unpack_from("<Q", data, footer + 9)
    assert start and data[footer] == 0x02
    for length in (2**62, 2**40, len(data) * 3):  # past the file's end, or absurd
        bad = bytearray(data)
        bad[start + 1:start + 9] = struct.pack("<Q", length)
        path = tmp_path / "bad.mcap"
        path.write_bytes(bytes(bad))
        log = read_log(path)  # never MemoryError: the chunks before are read
        assert log.messages
        assert read_run(path).t.size
        res = hmpc(["replay", path, "-q"], tmp_path)
        assert res.exit_code == 0, res.stderr


def test_memory_and_overflow_errors_of_the_content_are_damage(ball_run, monkeypatch):
    """A corrupted length field makes the MCAP library allocate gigabytes (MemoryError) or
    overflow: the index is given up, the chunks before the damage are kept."""
    import hmpc_cli.log.reader as reader

    whole = reader.read_log(ball_run / "run.mcap")

    def no_index(*_, **__):
        raise MemoryError()

    monkeypatch.setattr(reader, "make_reader", no_index)
    log = reader.read_log(ball_run / "run.mcap")  # the linear scan instead
    assert len(log.messages) == len(whole.messages) and log.complete
    calls = [0]
    real = reader.breakup_chunk

    def second_chunk_overflows(chunk, **kw):
        calls[0] += 1
        if calls[0] == 2:
            raise OverflowError("cannot fit 'int' into an index-sized integer")
        return real(chunk, **kw)

    monkeypatch.setattr(reader, "breakup_chunk", second_chunk_overflows)
    log = reader.read_log(ball_run / "run.mcap")
    assert not log.complete and "OverflowError" not in log.damage and log.damage
    assert 0 < len(log.messages) < len(whole.messages)


def test_a_run_stopped_at_its_start_says_so(tmp_path):
    from hmpc_cli.log.recorder import Recorder

    Recorder(tmp_path / "run.mcap")._file.close()  # the header only: killed at once
    res = hmpc(["replay", tmp_path / "run.mcap"], tmp_path)
    assert res.exit_code == 2
    assert "stopped before anything was logged" in res.stderr and "truncated" not in res.stderr
    (tmp_path / "run.mcap").write_bytes(b"")
    res = hmpc(["replay", tmp_path / "run.mcap"], tmp_path)
    assert res.exit_code == 2 and "stopped before anything was logged" in res.stderr


def _variants(data: bytes, n: int, seed: int) -> list[bytes]:
    """Damaged copies: byte flips (summary section too), truncations, length-field edits."""
    rng = random.Random(seed)
    out = []
    for k in range(n):
        b = bytearray(data)
        kind = k % 3
        if kind == 0:
            for _ in range(rng.randint(1, 3)):
                i = rng.randrange(len(b)) if rng.random() < 0.5 else \
                    rng.randrange(max(0, len(b) - 17000), len(b))
                b[i] ^= 1 << rng.randrange(8)
        elif kind == 1:
            b = b[: rng.randrange(len(b))]
        else:  # an MCAP record length (opcode, uint64): overwrite one somewhere
            i = rng.randrange(8, len(b) - 9)
            b[i + 1:i + 9] = struct.pack("<Q", rng.choice(
                [2**63 - 1, 2**32, len(b) * 2, rng.randrange(len(b))]))
        out.append(bytes(b))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("which", ["ball", "biped"])
def test_fuzzed_logs_never_give_an_internal_error(tmp_path, ball_run, biped_run, which):
    from hmpc_cli.log.damage import DamagedLogError
    from hmpc_cli.log.reader import read_log
    from hmpc_cli.log.rundata import read_run

    src = (ball_run if which == "ball" else biped_run) / "run.mcap"
    path = tmp_path / "v.mcap"
    for k, data in enumerate(_variants(src.read_bytes(), 150, seed=14)):
        path.write_bytes(data)
        try:
            read_log(path)
            read_run(path)
        except (ValueError, DamagedLogError):
            pass  # said clearly (not an MCAP file, damaged log)
        if k % 3 == 0:  # the command line too (a third of them: it prints tables)
            res = hmpc(["replay", path, "--export", tmp_path / "e"], tmp_path)
            assert res.exit_code in (0, 2), (k, res.stderr)
            assert "internal error" not in res.stderr, (k, res.stderr)


# ----------------------------------------------------------------- counts
def test_failed_walking_solves_are_counted(tmp_path):
    out = tmp_path / "b"
    res = hmpc(["run", BIPED, "--set", "sim.duration=0.3", "--set", "mpc.max_iter=2",
                "--out", out, "-q"], tmp_path)
    assert res.exit_code == 0, res.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["solver_failures"] > 0  # every candidate's walking MPC solve failed
    assert sum(s["failure_statuses"].values()) == s["solver_failures"]


def test_a_failed_candidate_solve_is_counted_once():
    from hmpc_cli.core.messages import ModeSchedule, Plan, PlannerResult, SolveStats
    from hmpc_cli.log.books import RunBooks

    def plan(t: float, guard: int, ok: bool) -> Plan:
        status = "Solve_Succeeded" if ok else "Maximum_Iterations_Exceeded"
        return Plan(t, None, SolveStats(status, ok, 9, 0.0, 1.0, 0.0),
                    ModeSchedule((0, 0), (guard,), (0.3,), t))

    log = RunBooks("biped", 0)
    bad, ok = plan(1.0, 3, False), plan(1.0, 4, True)
    log.planner_call(1.0, PlannerResult(None, None, 1.0, False, 0.1, 18, "",
                                        mpc_solves=(bad, ok)), False, "")
    assert log.result.solver_failures == 1
    log.count_solve(1.0, bad)
    assert log.result.solver_failures == 1  # the same solve, returned again: not twice
    log.count_solve(1.1, plan(1.1, 3, False))
    assert log.result.solver_failures == 2
    assert log.result.failure_statuses == {bad.stats.status: 2}


# ----------------------------------------------------------------- scene
def _scene_lines(log, entity_id: str) -> list[tuple[int, list[np.ndarray]]]:
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    out = []
    for m in log.raw:
        for e in SceneUpdate.FromString(m.data).entities:
            if e.id == entity_id:
                out.append((m.log_time_ns, [np.array([[p.x, p.z] for p in line.points])
                                            for line in e.lines]))
    return out


def test_biped_plan_and_rollout_lines_break_at_resets(biped_run):
    """No segment of /scene/plan or /scene/rollout joins the nodes before and after a
    reset (the legs swap there: the swing-foot trace jumped 0.47-0.74 m)."""
    from hmpc_cli.log.reader import read_log

    log = read_log(biped_run / "run.mcap")
    solves = {m.log_time_ns: m.data for m in log.topic("/mpc/solve")}
    plans = _scene_lines(log, "plan")
    assert plans and log.topic("/sim/event")
    for ns, lines in plans:
        nodes = solves[ns]["plan"]
        segs = [n["seg"] for n in nodes]
        assert len(set(segs)) == 2 and len(lines) == 4  # hip and swing foot, per swing
        per_seg = {s: np.array([[n["t"]] for n in nodes if n["seg"] == s]) for s in set(segs)}
        assert sorted(len(p) for p in lines) == sorted([len(v) for v in per_seg.values()] * 2)
        for pts in lines:  # within a swing the traced points move a few cm per node
            assert np.max(np.hypot(*np.diff(pts, axis=0).T)) < 0.3
    rollouts = _scene_lines(log, "rollout")
    assert rollouts
    for _, lines in rollouts:
        assert len(lines) == 4
        for pts in lines:
            assert np.max(np.hypot(*np.diff(pts, axis=0).T)) < 0.3


def test_a_path_whose_bytes_are_not_utf8_is_recorded_escaped(tmp_path):
    """``--out`` with a byte that is not UTF-8: the run crashed at t = 0 (UnicodeEncodeError
    writing /run/info's command line), and an export of a log there was reported as a
    damaged log. Every JSON hmpc writes now holds such a byte as ``\\xNN``."""
    import subprocess

    from conftest import BALL, cli_env, hmpc_command
    from hmpc_cli.log.reader import read_log

    out = os.fsdecode(os.fsencode(str(tmp_path)) + b"/run\xffbad")
    common = dict(env=cli_env(), capture_output=True, timeout=600)
    run = subprocess.run([*hmpc_command(), "run", str(BALL), "--out", out, "-q",
                          "--set", "sim.duration=0.3"], **common)
    assert run.returncode == 0, run.stderr
    info = next(m.data for m in read_log(Path(out) / "run.mcap").messages
                if m.topic == "/run/info")
    assert info["command"].endswith(f"--out '{tmp_path}/run\\xffbad' -q --set "
                                    "sim.duration=0.3")
    summary = (Path(out) / "summary.json").read_bytes().decode("utf-8")  # valid UTF-8
    assert json.loads(summary)["success"] in (True, False)
    export = tmp_path / "export"
    res = subprocess.run([*hmpc_command(), "replay", out, "--export", str(export), "-q"],
                         **common)
    assert res.returncode == 0, res.stderr
    assert json.loads((export / "info.json").read_text())["log"] == \
        f"{tmp_path}/run\\xffbad/run.mcap"


@pytest.fixture
def tiny_disk(tmp_path):
    yield from mounted_tmpfs(tmp_path / "tiny", "size=16k", "a full temporary directory")


def test_verify_with_a_full_temporary_directory_names_it(ball_run, tiny_disk, monkeypatch):
    """The re-run's log did not fit in TMPDIR: 'error: cannot write: No space left on
    device', naming neither the file nor the step."""
    import tempfile

    monkeypatch.setenv("TMPDIR", str(tiny_disk))
    monkeypatch.setattr(tempfile, "tempdir", None)  # read TMPDIR again
    res = hmpc(["replay", ball_run, "--verify", "-q"])
    assert res.exit_code == 2, res.output
    assert res.stderr.splitlines() == [
        f"error: {Path(ball_run) / 'run.mcap'}: --verify: cannot write the re-run's log in "
        f"{tiny_disk} (No space left on device): point TMPDIR at a directory with room for "
        "it"]


def test_printable_and_a_set_value_that_is_not_utf8():
    """A lone surrogate no byte stands for raised in printable; a --set value with a byte
    that is not UTF-8 crashed the run writing scenario.toml (exit 1): now exit 2, one
    line, nothing written."""
    from hmpc_cli.core.text import printable

    assert printable("a\udcffb") == "a\\xffb" and printable("a\ud800b") == "a\\ud800b"
    assert printable("plain é") == "plain é"
    bad = os.fsdecode(b'description="a\xffb"')
    res = hmpc(["run", str(REPO / "scenarios" / "ball.toml"), "--set", bad, "--out",
                "never"], None)
    assert res.exit_code == 2, res.output
    assert "--set 'description=\"a\\xffb\"': holds bytes that are not UTF-8 text " \
        "(shown as \\xNN); give the value in UTF-8" in res.stderr, res.stderr


def test_a_text_file_given_as_a_log_is_named_as_text(tmp_path):
    """A summary.json given where a run log goes: 'not an MCAP file', said in words (it
    printed the first bytes as a Python bytes literal)."""
    from hmpc_cli.log.reader import read_log

    (tmp_path / "summary.json").write_text('{\n  "scenario": "ball"\n}\n')
    (tmp_path / "noise.bin").write_bytes(bytes(range(200, 256)))
    for name, why in (("summary.json", " (it reads as text: a summary.json or a scenario?)"),
                      ("noise.bin", "")):
        with pytest.raises(ValueError) as err:
            read_log(tmp_path / name)
        assert str(err.value) == f"{tmp_path / name} is not an MCAP file{why}"
