"""``hmpc replay``: timeline, filters, export, verify and damaged or foreign files."""

from __future__ import annotations

import csv
import dataclasses
import json
import re
import textwrap
from collections import Counter
from pathlib import Path

import pytest
from typer.testing import CliRunner

from conftest import SCENARIOS
from hmpc_cli.cli.app import app
from hmpc_cli.log.recorder import Recorder
from hmpc_cli.log.reader import read_log

ENV = {"COLUMNS": "220", "NO_COLOR": "1", "TERM": "dumb"}


def _run(scenario: str, out: Path, *overrides: str) -> Path:
    """One short run in this process; returns its run directory."""
    from hmpc_cli.run.runner import run_scenario
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(SCENARIOS / scenario, list(overrides))
    run_scenario(sc, text, out)
    return out


def replay(*args: str):
    """``hmpc replay ARGS`` in this process."""
    res = CliRunner().invoke(app, ["replay", *map(str, args)], env=ENV)
    assert "Traceback" not in res.output, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    return res


@pytest.fixture(scope="module")
def ball(tmp_path_factory) -> Path:
    """A 0.6 s disturbed ball run, every simulator step logged (several chunks)."""
    return _run("ball_disturbed.toml", tmp_path_factory.mktemp("ball") / "run",
                "sim.duration=0.6", "sim.log_rate_hz=600")


@pytest.fixture(scope="module")
def ball_log(ball):
    return read_log(ball / "run.mcap")


@pytest.fixture(scope="module")
def biped(tmp_path_factory) -> Path:
    """A 0.6 s biped run on the stairs (two steps)."""
    return _run("biped_stairs.toml", tmp_path_factory.mktemp("biped") / "run",
                "sim.duration=0.6")


def _rows(output: str, kind: str) -> list[str]:
    """The timeline rows of one kind (contact, plan, solve, solves)."""
    return [line for line in output.splitlines()
            if re.match(rf"^\W*\d+\.\d{{4}}\W+{kind}\W", line)]


def _solves_in(output: str) -> int:
    """Solves in the timeline: single rows plus the summarised runs."""
    runs = sum(int(re.search(r"\.\.\. (\d+) solves ok", r).group(1))
               for r in _rows(output, "solves"))
    return len(_rows(output, "solve")) + runs


def test_ball_identity_summary_and_timeline(ball, ball_log) -> None:
    res = replay(ball)
    assert res.exit_code == 0, res.output
    out = res.output
    assert "ball_disturbed" in out and "complete" in out
    assert re.search(r"command\W+\S", out)  # the command line is recorded
    assert "success" in out and "contacts_by_guard" in out
    assert len(_rows(out, "contact")) == len(ball_log.topic("/sim/event")) > 0
    assert len(_rows(out, "plan")) == len(ball_log.topic("/planner/plan")) == 1
    assert _solves_in(out) == len(ball_log.topic("/mpc/solve")) > 2
    assert len(_rows(out, "solves")) >= 1  # ordinary solves are summarised by default
    assert "softened" in out  # this trial softens a guard-crossing solve
    assert "disturbance:" in out and "wx" in out and "wy" in out
    # how the NLPs were built (tests: SX, the cache's default mode)
    assert re.search(r"NLP build\W+miss: not compiled", out)


def test_a_description_the_overrides_outdate_says_so(tmp_path) -> None:
    """`hmpc run ball.toml --set mpc.rate_hz=20` then `hmpc replay` showed the file's
    "10 Hz fixed-mode MPC" as the run's description, with nothing to say it was not."""
    out = tmp_path / "r"
    ran = CliRunner().invoke(app, ["run", str(SCENARIOS / "ball.toml"), "--set",
                                   "mpc.rate_hz=20", "--set", "sim.duration=0.1", "--out",
                                   str(out), "-q"])
    assert ran.exit_code == 0, ran.output
    text = " ".join(replay(out).output.split())
    assert "10 Hz fixed-mode MPC, hybrid plan once at t = 0 (the scenario file's; the " \
        "overrides below changed the run)" in text, text
    assert "(the scenario file's" not in " ".join(replay(
        _run("ball.toml", tmp_path / "plain", "sim.duration=0.1")).output.split())
    seeded = tmp_path / "seeded"  # --seed alone leaves the description true
    ran = CliRunner().invoke(app, ["run", str(SCENARIOS / "ball.toml"), "--seed", "3", "--out",
                                   str(seeded), "-q"])
    assert ran.exit_code == 0 and "(the scenario file's" not in replay(seeded).output


def test_all_shows_every_solve(ball, ball_log) -> None:
    out = replay(ball, "--all").output
    assert len(_rows(out, "solve")) == len(ball_log.topic("/mpc/solve"))
    assert not _rows(out, "solves")


@pytest.mark.slow
def test_biped_timeline(biped) -> None:
    log = read_log(biped / "run.mcap")
    res = replay(biped / "run.mcap", "--all")
    assert res.exit_code == 0, res.output
    assert len(_rows(res.output, "contact")) == len(log.topic("/sim/event")) >= 1
    assert len(_rows(res.output, "solve")) == len(log.topic("/mpc/solve"))
    assert len(_rows(res.output, "plan")) == len(log.topic("/planner/plan")) >= 2
    assert "biped" in res.output and "single_support" in res.output


def test_time_and_topic_filters(ball, ball_log) -> None:
    out = replay(ball, "--from", "0.1", "--to", "0.3", "--all").output
    times = [float(r.split()[1]) for r in _rows(out, r"(contact|plan|solve)")]
    expected = [m for m in ball_log.messages if m.topic in ("/sim/event", "/mpc/solve",
                                                            "/planner/plan")
                and 0.1 - 1e-12 <= m.t <= 0.3 + 1e-12]
    assert times and all(0.1 - 1e-9 <= t <= 0.3 + 1e-9 for t in times)
    assert len(times) == len(expected)
    for name in ("/mpc/solve", "mpc/solve", "solve"):
        out = replay(ball, "--topic", name).output
        assert not _rows(out, "contact") and not _rows(out, "plan")
        assert _solves_in(out) == len(ball_log.topic("/mpc/solve"))
    out = replay(ball, "--topic", "event", "--topic", "plan").output
    assert len(_rows(out, "contact")) == len(ball_log.topic("/sim/event"))
    assert _solves_in(out) == 0


def test_unknown_topic(ball) -> None:
    res = replay(ball, "--topic", "camera")
    assert res.exit_code == 2
    assert "unknown topic 'camera'" in res.output and "/mpc/solve" in res.output


def test_csv_export(ball, ball_log, tmp_path) -> None:
    out = tmp_path / "csv"
    res = replay(ball, "--export", out)
    assert res.exit_code == 0, res.output
    counts: dict[str, int] = {}
    for m in ball_log.messages:
        counts[m.topic] = counts.get(m.topic, 0) + 1
    for topic, n in counts.items():
        with open(out / (topic.strip("/").replace("/", "_") + ".csv")) as f:
            rows = list(csv.DictReader(f))
        assert len(rows) == n, topic
    with open(out / "mpc_solve.csv") as f:
        header = next(csv.reader(f))
    assert {"t", "status", "iterations", "wall_time", "schedule.t0", "detail.shifted"} <= \
        set(header)
    with open(out / "mpc_solve_plan.csv") as f:
        rows = list(csv.DictReader(f))
    assert set(rows[0]) >= {"msg", "msg_t", "index", "t", "seg", "mode_name", "px", "vy", "ux"}
    with open(out / "sim_state.csv") as f:
        header = next(csv.reader(f))
    assert {"t", "x.px", "x.vy", "u.uy", "w.wy", "mode", "mode_name"} <= set(header)
    with open(out / "mpc_solve_plan.csv") as f:  # one row per planned node
        rows = list(csv.DictReader(f))
    assert len(rows) == sum(len(m.data["plan"]) for m in ball_log.topic("/mpc/solve"))
    assert list(rows[0])[:5] == ["msg", "msg_t", "index", "t", "seg"]
    info = json.loads((out / "info.json").read_text())
    assert info["run_info"]["scenario_name"] == "ball_disturbed"
    assert "[disturbance]" in info["scenario_toml"]


def test_every_child_table_joins_its_topics_table_on_msg(ball, ball_log, tmp_path) -> None:
    """Every table starts with msg (the message's position in its topic) and msg_t (its log
    time), and each row of a list's table (the plan's nodes, the rollout, the run info's
    lists) finds exactly one row of its topic's table on msg, with the same msg_t text
    (the parent's t, the message's float, had matched 2 solves in 32)."""
    out = tmp_path / "csv"
    assert replay(ball, "--export", out).exit_code == 0
    tables = {}
    for path in out.glob("*.csv"):
        with open(path, newline="") as f:
            tables[path.stem] = list(csv.DictReader(f))
    topics = {m.topic.strip("/").replace("/", "_") for m in ball_log.messages}
    children = set(tables) - topics
    assert {"mpc_solve_plan", "planner_plan_rollout", "run_info_geometry_static"} <= children
    for name, rows in tables.items():
        assert rows and list(rows[0])[:2] == ["msg", "msg_t"], name
        if name in topics:
            assert [r["msg"] for r in rows] == [str(i) for i in range(len(rows))], name
    for child in children:
        parent = {r["msg"]: r["msg_t"] for r in tables[max(
            (t for t in topics if child.startswith(t + "_")), key=len)]}
        assert [r for r in tables[child] if parent.get(r["msg"]) != r["msg_t"]] == [], child
    nodes = Counter(r["msg"] for r in tables["mpc_solve_plan"])
    assert [nodes[r["msg"]] for r in tables["mpc_solve"]] == \
        [len(m.data["plan"]) for m in ball_log.topic("/mpc/solve")]


def test_an_empty_object_or_list_writes_no_cell(ball, tmp_path) -> None:
    """An empty container's cells are its elements', none (it wrote the strings "[]" and
    "{}" into a column beside the non-empty ones' x[0] columns or child table)."""
    from hmpc_cli.analysis.export import flatten

    nested: dict = {}
    row = flatten({"a": [], "b": {}, "c": [1, "x"], "d": {"e": 1, "f": {}}, "g": [{"h": 1}],
                   "k": []}, nested)
    assert row == {"c[0]": 1, "c[1]": "x", "d.e": 1} and nested == {"g": [{"h": 1}]}
    assert flatten({"plan": []}, nested := {}) == {} and nested == {}
    out = tmp_path / "csv"
    assert replay(ball, "--export", out).exit_code == 0
    for path in out.glob("*.csv"):
        with open(path, newline="") as f:
            cells = [c for r in csv.reader(f) for c in r]
        assert "[]" not in cells and "{}" not in cells, path.name
    with open(out / "sim_state.csv", newline="") as f:  # the ball has no body points
        assert not [c for c in next(csv.reader(f)) if c.startswith("body")]


def test_export_after_filters(ball, ball_log, tmp_path) -> None:
    res = replay(ball, "--topic", "disturbance", "--to", "0.2", "--export", tmp_path)
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["disturbance.csv", "info.json"]
    with open(tmp_path / "disturbance.csv") as f:
        n = len(list(csv.DictReader(f)))
    assert n == len([m for m in ball_log.topic("/disturbance") if m.t <= 0.2 + 1e-12])


def test_an_export_replaces_an_earlier_one_and_refuses_other_files(ball, tmp_path) -> None:
    """Exporting again into an earlier export's directory with other filters leaves no
    stale topic table beside it; a directory holding other files is refused (exit 2,
    nothing written), before the log is read."""
    out = tmp_path / "e"
    assert replay(ball, "--export", out).exit_code == 0
    assert "sim_state.csv" in {p.name for p in out.iterdir()}
    res = replay(ball, "--topic", "disturbance", "--export", out)
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in out.iterdir()) == ["disturbance.csv", "info.json"]
    assert json.loads((out / "info.json").read_text())["files"] == ["disturbance.csv"]
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "sim_state.csv").write_text("my own table\n")
    res = replay(ball, "--export", mine)
    assert res.exit_code == 2
    assert res.stderr == (f"error: --export {mine}: is not empty (sim_state.csv) and holds no "
                          "earlier export (its info.json): choose a new or empty directory\n")
    assert [p.name for p in mine.iterdir()] == ["sim_state.csv"]
    assert (mine / "sim_state.csv").read_text() == "my own table\n"


def test_parquet_export(ball, tmp_path) -> None:
    res = replay(ball, "--export", tmp_path / "pq", "--format", "parquet")
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        assert res.exit_code == 2 and "pip install pyarrow" in res.output
        return
    assert res.exit_code == 0, res.output
    assert (tmp_path / "pq" / "mpc_solve.parquet").is_file()


def test_verify_identical(ball, ball_log) -> None:
    """Every message of every topic is compared, the 3D scene's protobuf ones too."""
    res = replay(ball, "--verify")
    assert res.exit_code == 0, res.output
    topics = {m.topic for m in ball_log.messages} | {m.topic for m in ball_log.raw}
    assert {t for t in topics if t.startswith("/scene/")} == {
        "/scene/static", "/scene/body", "/scene/plan", "/scene/rollout"}
    n = len(ball_log.messages) + len(ball_log.raw)
    assert f"identical ({n} messages on {len(topics)} topics)" in res.output


def test_verify_finds_a_changed_scene_message(ball, ball_log, tmp_path) -> None:
    """One byte of one /scene/plan message changed: the scene is compared byte for byte."""
    from hmpc_cli.analysis.replay import scene_divergence

    raw = list(ball_log.raw)
    k = next(i for i, m in enumerate(raw) if m.topic == "/scene/plan")
    edited = [*raw[:k], dataclasses.replace(raw[k], data=raw[k].data[:-1] + b"\x00"),
              *raw[k + 1:]]
    div = scene_divergence(raw, edited)
    assert (div.topic, div.path, div.t) == ("/scene/plan", "(protobuf message)", raw[k].t)
    assert scene_divergence(raw, raw) is None
    short = scene_divergence(raw, raw[:-1])
    assert short.path == "(message count)" and scene_divergence(raw[:-1], raw, True) is None


def test_a_scene_topic_is_named_as_one(ball) -> None:
    res = replay(ball, "--topic", "/scene/plan")
    assert res.exit_code == 2
    assert "'/scene/plan' is a 3D-scene topic (protobuf, for Foxglove or Lichtblick): " \
        "--topic selects the JSON topics" in res.output, res.output


def _rewrite(src: Path, dst: Path, scenario: str | None) -> Path:
    """A copy of a log with another (or no) scenario.toml attachment."""
    log = read_log(src)
    with Recorder(dst) as rec:
        for topic, schema in log.schemas.items():
            rec.add_topic(topic, "hmpc.copy", schema)
        if scenario is not None:
            rec.add_attachment("scenario.toml", scenario.encode(), "application/toml")
        for m in log.messages:
            rec.write(m.topic, m.t, m.data)
    return dst


def test_verify_names_the_first_divergence(ball, ball_log, tmp_path) -> None:
    text = (ball / "scenario.toml").read_text()
    assert 'policy = "once"' in text
    edited = _rewrite(ball / "run.mcap", tmp_path / "edited.mcap",
                      text.replace('policy = "once"', 'policy = "on_contact"'))
    res = replay(edited, "--verify")
    assert res.exit_code == 1, res.output
    # the re-run replans at the first contact; the recorded run planned once
    hit = re.search(r"diverged at t = ([\d.]+) s on /planner/plan, field \(message count\): "
                    r"recorded 1, re-run \d+", res.output)
    assert hit, res.output
    first = ball_log.topic("/sim/event")[0].t  # replanned at the step after the contact
    assert first <= float(hit.group(1)) <= first + 1 / 600 + 1e-9


def test_verify_without_a_rebuildable_scenario(ball, tmp_path) -> None:
    res = replay(_rewrite(ball / "run.mcap", tmp_path / "none.mcap", None), "--verify")
    assert res.exit_code == 2 and "no scenario.toml attached" in res.output
    bad = (ball / "scenario.toml").read_text().replace('name = "ball"', 'name = "no_such"')
    res = replay(_rewrite(ball / "run.mcap", tmp_path / "bad.mcap", bad), "--verify")
    assert res.exit_code == 2 and "cannot be rebuilt" in res.output and "no_such" in res.output


def test_verify_of_a_run_a_stop_signal_ended_compares_up_to_the_stop(tmp_path) -> None:
    """The re-run goes on past the stop: a stopped run is compared up to where it ended
    (its summary and the state sample the stop wrote left out); it was reported as
    diverged on the message count of its first topic."""
    import signal

    from hmpc_cli.core import signals
    from hmpc_cli.run.runner import execute_run, prepare
    from hmpc_cli.run.scenario import load_scenario

    sc, text = load_scenario(SCENARIOS / "ball_disturbed.toml", ["sim.duration=0.6"])
    prepared = prepare(sc)
    step, calls = prepared.plant.step, []

    def stopped_at_step_200(*args, **kwargs):
        calls.append(1)
        if len(calls) == 200:  # the loop's check after this step stops the run
            signals._STATE.signum = int(signal.SIGTERM)
        return step(*args, **kwargs)

    prepared.plant.step = stopped_at_step_200
    try:
        with pytest.raises(KeyboardInterrupt):
            execute_run(prepared, text, tmp_path / "run")
    finally:
        signals.reset()
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["reason"] == "interrupted (SIGTERM)"
    assert summary["t_end"] == pytest.approx(200 / 600)
    res = replay(tmp_path / "run", "--verify")
    assert res.exit_code == 0, res.output
    assert re.search(r"identical \(\d+ messages on \d+ topics\) up to t = 0\.3333 s \(a "
                     r"stop signal ended the run there\)", " ".join(res.output.split())), \
        res.output


def test_verify_refuses_a_damaged_log_and_a_measured_latency_run(ball, tmp_path) -> None:
    """A log missing a chunk, and a run that charged its measured compute time, cannot
    match any re-run: exit 2 with the reason (they were reported as diverged, exit 1)."""
    path = _flipped(ball / "run.mcap", 1, tmp_path / "flipped.mcap")
    line = _error_line(replay(path, "--verify"))
    assert line.startswith(f"error: {path}: --verify: damaged log (1 of ")
    assert line.endswith("what a re-run would be compared with is not all there, so no "
                         "re-run can be compared with it (hmpc replay shows what it holds "
                         "intact)")
    measured = _run("ball.toml", tmp_path / "measured", "sim.duration=0.1",
                    'sim.latency="measured"')
    line = _error_line(replay(measured, "--verify"))
    assert line.startswith(f"error: {measured / 'run.mcap'}: --verify: the run charged its "
                           'measured compute time (sim.latency = "measured"): ')


def _record_at(path: Path, opcode: int) -> int:
    """The byte offset of the first top-level record of ``opcode`` in an MCAP file."""
    import struct

    data, pos = path.read_bytes(), 8
    while struct.unpack("<B", data[pos:pos + 1])[0] != opcode:
        pos += 9 + struct.unpack("<Q", data[pos + 1:pos + 9])[0]
    return pos


def test_a_damaged_metadata_or_attachment_record_is_damage_not_a_cut(ball, tmp_path) -> None:
    """A byte flipped in the run's metadata record of a finished log read as a log cut
    short after /run/info (2 messages: --verify said identical, exit 0); one changed in the
    attached scenario went unchecked (the mcap reader skips its CRC: --verify blamed the
    run, exit 1). Now both are damage: every message kept, --verify exits 2."""
    whole = (ball / "run.mcap").read_bytes()
    n = len(read_log(ball / "run.mcap").messages)
    meta = bytearray(whole)
    meta[_record_at(ball / "run.mcap", 0x0C) + 13] ^= 0xFF  # inside the record's name
    scenario = bytearray(whole)
    at = whole.index(b"[system]", _record_at(ball / "run.mcap", 0x09))
    scenario[at:at + 8] = b"[sistem]"
    for name, data, says in (
            ("meta.mcap", meta, "its metadata records are damaged, left out"),
            ("scenario.mcap", scenario, "attachment(s) 'scenario.toml' damaged (CRC), left "
                                        "out")):
        path = tmp_path / name
        path.write_bytes(bytes(data))
        log = read_log(path)
        assert log.damage.startswith(says) and len(log.messages) == n, log.damage
        line = _error_line(replay(path, "--verify"))
        assert line.startswith(f"error: {path}: --verify: damaged log ({says}")
    assert "scenario.toml" not in read_log(tmp_path / "scenario.mcap").attachments


def test_replay_refuses_format_alone_and_a_verify_refusal_before_any_export(ball,
                                                                           tmp_path) -> None:
    """``--format`` without ``--export`` was ignored (exit 0); ``--export --verify`` of a
    log --verify refuses wrote the export, then exited 2."""
    alone = _error_line(replay(ball, "--format", "parquet"))
    assert alone == "error: --format parquet: the format of --export's tables; give " \
                    "--export DIR too"
    path = _flipped(ball / "run.mcap", 1, tmp_path / "flipped.mcap")
    out = tmp_path / "export"
    line = _error_line(replay(path, "--export", str(out), "--verify"))
    assert line.startswith(f"error: {path}: --verify: damaged log (1 of ")
    assert not out.exists()


def _error_line(res) -> str:
    lines = [line for line in res.output.splitlines() if line.startswith("error: ")]
    assert res.exit_code == 2 and len(lines) == 1, res.output
    return lines[0]


@pytest.mark.parametrize("where", ["0", "8", "100", "half", "after-chunk-1", "last-10"])
def test_truncated_file(ball, tmp_path, where) -> None:
    from mcap.reader import make_reader

    data = (ball / "run.mcap").read_bytes()
    with open(ball / "run.mcap", "rb") as f:
        second = make_reader(f).get_summary().chunk_indexes[1].chunk_start_offset
    cut = {"0": 0, "8": 8, "100": 100, "half": len(data) // 2, "after-chunk-1": second + 10,
           "last-10": len(data) - 10}[where]
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[:cut])
    if cut == 0:
        assert _error_line(replay(path)).startswith(f"error: {path}: empty file")
        return
    log = read_log(path)
    assert where not in ("after-chunk-1", "last-10") or log.messages
    res = replay(path)
    if not log.messages:  # nothing completed: one error line
        assert f"{path}: no message could be read" in _error_line(res)
        return
    assert res.exit_code == 0, res.output
    assert f"cut short at t = {max(m.t for m in log.messages):.3f} s" in res.output
    assert ("no summary (the run did not finish)" in res.output) == (where != "last-10")


def test_bit_flip_inside_a_chunk(ball, ball_log, tmp_path) -> None:
    from mcap.reader import make_reader

    data = bytearray((ball / "run.mcap").read_bytes())
    with open(ball / "run.mcap", "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 2
    second = chunks[1]
    data[second.chunk_start_offset + second.chunk_length // 2] ^= 0x10
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(data))
    res = replay(path)
    assert res.exit_code == 0, res.output
    assert "damaged" in res.output and "the chunks read are shown" in res.output
    # the footer and chunk index are intact: every other chunk is read, the summary too
    log, whole = read_log(path), read_log(ball / "run.mcap")
    assert not log.complete and log.damage.startswith(
        f"1 of {len(chunks)} chunks left out: chunk 2 (t = ")
    assert log.topic("/run/summary") == whole.topic("/run/summary")
    lost = {(m.topic, m.log_time_ns) for m in whole.messages} - {
        (m.topic, m.log_time_ns) for m in log.messages}
    assert lost and all(second.message_start_time <= t <= second.message_end_time
                        for _, t in lost)
    assert "did not finish" not in res.output and "no summary" not in res.output
    first = chunks[0]
    data[first.chunk_start_offset + first.chunk_length // 2] ^= 0x10
    path.write_bytes(bytes(data))
    assert _error_line(replay(path)).startswith(  # the chunk with /run/info is lost
        f"error: {path}: damaged log: its /run/info could not be read: 2 of {len(chunks)} "
        "chunks left out: chunk 1 (t = ")


def _flipped(log: Path, chunk: int, path: Path) -> Path:
    """``log`` with one bit flipped in the middle of its chunk ``chunk``, written to ``path``."""
    from mcap.reader import make_reader

    data = bytearray(log.read_bytes())
    with open(log, "rb") as f:
        index = make_reader(f).get_summary().chunk_indexes[chunk]
    data[index.chunk_start_offset + index.chunk_length // 2] ^= 0x10
    path.write_bytes(bytes(data))
    return path


def test_other_commands_name_the_damage_that_lost_what_they_need(ball, tmp_path) -> None:
    """A log whose first chunk (/run/info, the first solves) is damaged: ``plot fig2`` and
    ``tube --runs`` say the log is damaged beside what they miss (they said "the log names
    no system" and "not a run of this scenario's system"); a missing ``--runs``/``--states``
    log is named by its option, not called damaged."""
    path = _flipped(ball / "run.mcap", 0, tmp_path / "flipped.mcap")
    damage = "(damaged log: 1 of "
    fig2 = CliRunner().invoke(app, ["plot", "fig2", str(path), "--out", str(tmp_path / "f")])
    assert fig2.exit_code == 2 and "Traceback" not in fig2.output
    assert f"error: {path}: the log names no system {damage}" in fig2.output, fig2.output
    scenario = str(SCENARIOS / "ball_disturbed.toml")
    for option, log, says in (
            ("--runs", path, f"error: --runs {path}: not a run of this scenario's system "
                             f"(its log names no system) {damage}"),
            ("--runs", tmp_path / "nowhere.mcap", f"error: --runs {tmp_path}/nowhere.mcap: "
                                                  "no such run log"),
            ("--states", tmp_path / "nowhere.mcap", f"error: --states {tmp_path}/nowhere.mcap"
                                                    ": no such run log")):
        res = CliRunner().invoke(app, ["tube", scenario, option, str(log), "--samples", "10",
                                       "--out", str(tmp_path / "t")])
        assert res.exit_code == 2 and "Traceback" not in res.output, res.output
        assert says in " ".join(res.output.split()), res.output
    assert not (tmp_path / "f").exists() and not (tmp_path / "t").exists()


def test_a_figure_from_a_log_not_read_whole_says_so(ball, tmp_path) -> None:
    """A damaged (a chunk left out) or cut-short log still draws what it holds, with a
    warning naming the damage (plot timing counted 0 of 26 solves of a 32-solve run, and
    fig2 numbered its solves from the first one read, without a word)."""
    from mcap.reader import make_reader

    damaged = _flipped(ball / "run.mcap", 1, tmp_path / "flipped.mcap")
    with open(ball / "run.mcap", "rb") as f:
        third = make_reader(f).get_summary().chunk_indexes[2].chunk_start_offset
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((ball / "run.mcap").read_bytes()[:third + 10])
    for log, note in ((damaged, "(damaged log: 1 of "), (cut, "(the log is cut short)")):
        for figure in ("timing", "fig2"):
            res = CliRunner().invoke(app, ["plot", figure, str(log), "--out",
                                           str(tmp_path / figure), "--formats", "png"])
            assert res.exit_code == 0, res.output
            assert f"warning: {log}: the figure shows what the log holds {note}" in \
                res.stderr, res.output
        res = CliRunner().invoke(app, ["tube", str(SCENARIOS / "ball_disturbed.toml"),
                                       "--runs", str(log), "--samples", "10", "--out",
                                       str(tmp_path / "t"), "-q"])
        assert res.exit_code == 0, res.output
        assert f"warning: --runs {log.name}: tube vs reality uses what the log holds " \
            f"{note}" in res.stderr, res.output
        res = CliRunner().invoke(app, ["tube", str(SCENARIOS / "ball_disturbed.toml"),
                                       "--states", str(log), "--samples", "10", "--out",
                                       str(tmp_path / "t"), "-q"])
        assert res.exit_code == 0, res.output  # --states said nothing of the damage
        assert f"warning: --states {log}: the region spans the states the log holds " \
            f"{note}" in res.stderr, res.output
    res = CliRunner().invoke(app, ["plot", "timing", str(ball), "--out", str(tmp_path / "w"),
                                   "--formats", "png"])
    assert res.exit_code == 0 and "warning" not in res.stderr, res.output


def test_tube_refuses_a_run_given_twice_and_a_margins_file_over_its_own_outputs(
        ball, tmp_path) -> None:
    """``--runs R --runs R/run.mcap`` counted R's periods twice; ``--write`` naming one of
    the files written to --out replaced it with the margins file; a directory where an
    output file goes was found after the others were written. Each: exit 2, nothing
    written."""
    scenario = str(SCENARIOS / "ball_disturbed.toml")
    out = tmp_path / "t"
    twice = CliRunner().invoke(app, ["tube", scenario, "--runs", str(ball), "--runs",
                                     str(ball / "run.mcap"), "--samples", "10", "--out",
                                     str(out)])
    assert twice.exit_code == 2 and "Traceback" not in twice.output, twice.output
    assert twice.stderr.splitlines() == [
        f"error: --runs {ball / 'run.mcap'}: the same log as --runs {ball} "
        f"({(ball / 'run.mcap').resolve()}); give each run once"], twice.output
    for name in ("tube.json", "tube_diameter.png", "tube_reality.svg"):
        res = CliRunner().invoke(app, ["tube", scenario, "--samples", "10", "--out", str(out),
                                       "--write", str(out / name)])
        assert res.exit_code == 2, res.output
        assert res.stderr.splitlines() == [
            f"error: --write {out / name}: is {name}, a file this command writes to --out "
            f"{out}: name the margins file otherwise (e.g. {out / 'margins.toml'})"]
    assert not out.exists()
    (out / "tube_margins.png").mkdir(parents=True)  # written after tube.json and 3 figures
    res = CliRunner().invoke(app, ["tube", scenario, "--samples", "10", "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert res.stderr.splitlines() == [
        f"error: --out {out}: {out / 'tube_margins.png'} is a directory, where this command "
        "writes a file: remove it or choose another --out"]
    assert [p.name for p in out.iterdir()] == ["tube_margins.png"]


def test_a_log_read_for_some_topics_is_the_whole_read_of_those(ball, tmp_path) -> None:
    """read_log(topics=...) keeps those topics' messages, as the whole read has them, and
    still CRC-checks every chunk; read_run(with_plans=False) is the whole read without the
    plans."""
    import pickle

    from hmpc_cli.log.rundata import TRAJECTORY_TOPICS, read_run

    def kept(log):
        return [(m.topic, m.log_time_ns, m.data) for m in log.messages
                if m.topic in TRAJECTORY_TOPICS]

    whole, part = read_log(ball / "run.mcap"), read_log(ball / "run.mcap", TRAJECTORY_TOPICS)
    assert {m.topic for m in whole.messages} > TRAJECTORY_TOPICS >= {m.topic for m in
                                                                     part.messages}
    assert kept(part) == kept(whole) and part.messages and not part.raw
    assert part.complete and part.schemas == whole.schemas and part.metadata == whole.metadata
    full, light = read_run(ball), read_run(ball, with_plans=False)
    assert full.solves and full.planner and not light.solves and not light.planner
    for f in dataclasses.fields(full):  # arrays, records and lists of them: their pickles
        if f.name not in ("solves", "planner"):
            assert pickle.dumps(getattr(full, f.name)) == pickle.dumps(getattr(light, f.name))
    # a damaged chunk is found whichever topics are read
    path = _flipped(ball / "run.mcap", 1, tmp_path / "flipped.mcap")
    whole, part = read_log(path), read_log(path, TRAJECTORY_TOPICS)
    assert not part.complete and part.damage == whole.damage != ""
    assert kept(part) == kept(whole) and part.messages


def _foreign_log(path: Path, topic: str, encoding: str, schema: tuple, payloads: list
                 ) -> Path:
    """An MCAP file another tool wrote: one channel, its messages at t = 0, 1, ... ns."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="other")
        cid = w.register_channel(topic, encoding, w.register_schema(*schema))
        for i, data in enumerate(payloads):
            w.add_message(cid, i, data, i)
        w.finish()
    return path


def test_bad_files(ball, tmp_path) -> None:
    import random

    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    noise = tmp_path / "noise.bin"
    noise.write_bytes(random.Random(0).randbytes(4000))
    foreign = _foreign_log(tmp_path / "foreign.mcap", "/camera", "json",
                           ("Cam", "jsonschema", b"{}"), [b'{"frame": 1}'])
    (tmp_path / "dir").mkdir()
    cases = {tmp_path / "missing.mcap": "no such file",
             tmp_path / "dir": "a directory without run.mcap",
             empty: "empty file", noise: "not an MCAP file",
             foreign: "not an hmpc run log (no /run/info; its topics: /camera)"}
    for path, what in cases.items():  # an empty file: "empty file: the run was stopped ..."
        assert _error_line(replay(path)).startswith(f"error: {path}: {what}")
    sweep = tmp_path / "sweep"  # a sweep's output directory: where its runs are
    (sweep / "runs").mkdir(parents=True)
    (sweep / "results.csv").write_text("run_id\n")
    said = (f"a sweep's output directory, not a run's: its runs are in {sweep / 'runs'}/"
            "<run id>")
    assert _error_line(replay(sweep)) == (
        f"error: {sweep}: a directory without run.mcap (or trace.mcap): {said}")
    stopped = tmp_path / "stopped"  # a sweep stopped before its table: its sweep file
    (stopped / "runs").mkdir(parents=True)
    (stopped / "sweep.toml").write_text('name = "s"\n')
    assert _error_line(replay(stopped)).endswith(said.replace(str(sweep), str(stopped)))
    from test_plot import make_app  # the figures of a run, given a sweep's directory
    for figure in ("timing", "fig2", "fig4"):
        res = CliRunner().invoke(make_app(), ["plot", figure, str(sweep)])
        assert res.exit_code == 2 and f"{sweep}: {said}" in res.output, (figure, res.output)


def test_a_log_without_json_messages_is_told_apart(ball, tmp_path) -> None:
    """A foreign log of non-JSON messages (a ROS 2 one) was 'the run was stopped before
    anything was logged'; a file cut inside its first chunk said 'its header only' though
    it holds the attached scenario too."""
    ros = _foreign_log(tmp_path / "ros.mcap", "/chatter", "cdr",
                       ("std_msgs/msg/String", "ros2msg", b"string data"),
                       [b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00"] * 5)
    assert _error_line(replay(ros)) == (
        f"error: {ros}: not an hmpc run log (no /run/info; its topics: /chatter)")
    from mcap.reader import make_reader

    with open(ball / "run.mcap", "rb") as f:
        first = make_reader(f).get_summary().chunk_indexes[0].chunk_start_offset
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((ball / "run.mcap").read_bytes()[:first + 100])
    assert _error_line(replay(cut)) == (
        f"error: {cut}: no message could be read: the run was stopped before anything was "
        f"logged ({first + 100} bytes: its header and attachment 'scenario.toml' only), or "
        "the file was cut short after them")


def test_bad_file_in_a_real_process(run_hmpc, tmp_path) -> None:
    (tmp_path / "x.mcap").write_bytes(b"\x89MCAP0\r\n\x01\x02")
    res = run_hmpc(["replay", "x.mcap"], tmp_path)
    assert res.returncode == 2 and "Traceback" not in res.stderr + res.stdout
    assert res.stderr.startswith("error: x.mcap: no message could be read")


def _named_layout_log(path: Path, info_extra: dict) -> Path:
    """A synthetic log in the named-field layout (states and plans as named objects).

    Its /sim/state's mode is a name when ``info_extra`` gives an older log version (a
    scalar of another kind, which replay reads as it is), else the mode's index, as the
    current version writes it (a name there is damage).
    """
    from hmpc_cli.log.topics import LOG_VERSION

    mode = 0 if info_extra.get("log_version") == LOG_VERSION else "out"
    with Recorder(path) as rec:
        for topic in ("/run/info", "/sim/state", "/disturbance", "/mpc/solve", "/sim/event",
                      "/planner/plan"):
            rec.add_topic(topic, "hmpc.any", {"type": "object"})
        rec.write("/run/info", 0.0, {"scenario_name": "named", "seed": 3, "system": "ball",
                                     "versions": {"hmpc": "9"}, **info_extra})
        rec.write("/planner/plan", 0.0, {"t": 0.0, "reason": "initial", "accepted": False,
                                         "reached_final": False, "cost": None,
                                         "wall_time": 0.01, "note": "no schedule"})
        for k in range(4):
            t = 0.1 * k
            rec.write("/sim/state", t, {"t": t, "x": {"px": 1.0 + t, "py": 2.0}, "mode": mode})
            rec.write("/disturbance", t, {"t": t, "w": {"fx": [1.0, -3.0, 2.0, 0.0][k],
                                                        "fy": 0.5}})
            rec.write("/mpc/solve", t, {
                "t": t, "reason": "period", "status": "Solve_Succeeded" if k != 2 else
                "Maximum_Iterations_Exceeded", "success": k != 2, "iterations": 5,
                "wall_time": 0.002, "cost": 1.0, "slack": 0.0, "adopted": k != 3,
                "plan": [{"t": t + 0.05 * i, "seg": 0, "x": {"px": 1.0, "py": 2.0},
                          "u": {"ux": -1.0}} for i in range(k + 2)]})
        rec.write("/sim/event", 0.15, {"t": 0.15, "guard_name": "floor", "mode_before": "out",
                                       "mode_after": "out", "scheduled": False})
    return path


def test_named_field_layout(tmp_path, monkeypatch) -> None:
    import hmpc_cli.analysis.replay as rp

    path = _named_layout_log(tmp_path / "named.mcap", {
        "log_version": 2, "argv": ["hmpc", "run", "x.toml", "--set", "sim.duration=1"],
        "overrides": ["sim.duration=1"]})
    monkeypatch.setattr(rp, "LOG_VERSION", 3)
    res = replay(path, "--export", tmp_path / "csv")
    assert res.exit_code == 0, res.output
    out = res.output
    assert "written by an older hmpc log version (2" in out
    assert "hmpc run x.toml --set sim.duration=1" in out and "sim.duration=1" in out
    assert "no summary (the run did not finish)" in out
    assert "REJECTED" in out and "no schedule" in out and "NOT scheduled" in out
    assert "FAILED Maximum_Iterations_Exceeded" in out and "not adopted" in out
    assert re.search(r"fx\W+3\W", out) and re.search(r"fy\W+0\.5\W+0\.5", out)
    with open(tmp_path / "csv" / "mpc_solve_plan.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 + 3 + 4 + 5
    assert list(rows[0]) == ["msg", "msg_t", "index", "t", "seg", "x.px", "x.py", "u.ux"]
    with open(tmp_path / "csv" / "sim_state.csv") as f:
        assert next(csv.reader(f)) == ["msg", "msg_t", "t", "x.px", "x.py", "mode"]


def test_current_log_version_has_no_note(tmp_path) -> None:
    from hmpc_cli.log.topics import LOG_VERSION

    out = replay(_named_layout_log(tmp_path / "v.mcap", {"log_version": LOG_VERSION})).output
    assert "log version" not in out and re.search(r"command\W+not recorded", out)
    mode_name = _named_layout_log(tmp_path / "v3.mcap", {"log_version": 2})  # an old layout
    res = replay(mode_name)  # read as it is: another version's scalars are not checked
    assert res.exit_code == 0 and "written by an older hmpc log version (2" in res.output
    old = replay(_named_layout_log(tmp_path / "v1.mcap", {"log_version": 1})).output
    assert "written by an older hmpc log version (1" in " ".join(old.split())


def test_an_untyped_version_1_log_is_replayed_not_called_damaged(tmp_path) -> None:
    """Log version 1 (no log_version; states, inputs and plans as plain arrays): replay
    reads it (its arrays are not objects of the current layout) and says its version;
    a scalar where an object or array belongs is still damage there."""
    path = tmp_path / "v1.mcap"

    def write(state_x) -> None:
        with Recorder(path) as rec:
            for topic in ("/run/info", "/sim/state", "/mpc/solve"):
                rec.add_topic(topic, "old", {"type": "object", "properties": {}})
            rec.write("/run/info", 0.0, {"scenario_name": "old", "seed": 3,
                                         "scenario": {"system": {"name": "ball"}},
                                         "state_names": ["px", "py"]})
            for k in range(3):
                rec.write("/sim/state", 0.1 * k, {"t": 0.1 * k, "x": state_x(k), "mode": 0,
                                                   "u": [0.0], "x_ref": [k, -k], "w": [0.0]})
            rec.write("/mpc/solve", 0.0, {"t": 0.0, "status": "ok", "success": True,
                                          "t_plan": [0.0, 0.1], "x_plan": [[0, 0], [1, -1]],
                                          "u_plan": [[0.0], [0.0]], "seg_plan": [0, 0]})

    write(lambda k: [k, -k])
    res = replay(path)
    assert res.exit_code == 0, res.output
    assert "written by an older hmpc log version (1" in " ".join(res.output.split())
    write(lambda k: 1.0 * k)
    assert _error_line(replay(path)) == (
        f"error: {path}: damaged log: its content cannot be read: /sim/state at t = 0 s: x: "
        "expected an object, got a number")


def test_figures_from_a_log_none_can_be_drawn_from_is_an_error(ball, tmp_path) -> None:
    """--figures on a log cut after 30 kB: no figure can be drawn, so the option fails
    (exit 2, each figure's reason on stderr, -q or not) and the directory it made goes;
    it printed the directory, exit 0, and left it empty."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes((ball / "run.mcap").read_bytes()[:30000])
    res = replay(cut, "--figures", tmp_path / "f", "-q")
    assert res.exit_code == 2, res.output
    lines = res.stderr.splitlines()
    assert lines[0] == f"error: --figures {tmp_path / 'f'}: no figure could be drawn from " \
                       "this log"
    assert [line.split(":")[1].strip() for line in lines[1:]] == [
        "fig2", "fig4", "timing", "scene animation"]
    assert not (tmp_path / "f").exists() and not res.stdout.strip()


def test_foreign_log_with_a_run_info_topic(tmp_path) -> None:
    path = tmp_path / "other.mcap"
    with Recorder(path) as rec:
        rec.add_topic("/run/info", "Other", {"type": "object"})
        rec.write("/run/info", 0.0, {"robot": "arm"})
    assert _error_line(replay(path)) == (
        f"error: {path}: not an hmpc run log (its /run/info has no scenario_name)")


@pytest.mark.slow
@pytest.mark.parametrize("system", ["ball", "biped"])
def test_figures_and_the_scene_animation(system, request, tmp_path) -> None:
    """--figures: the figures the system supports, the others named; a GIF of the scene."""
    run = request.getfixturevalue(system)
    res = replay(run, "--topic", "summary", "--figures", tmp_path / "f")
    assert res.exit_code == 0, res.output
    out = " ".join(res.output.split())
    drawn, skipped = ("fig2", "fig4") if system == "ball" else ("fig4", "fig2")
    assert f"figures: {drawn} written" in out and f"figures: {skipped} not drawn" in out
    assert "figures: timing written" in out  # every run with a solve
    assert (tmp_path / "f" / f"{drawn}.png").is_file()
    assert (tmp_path / "f" / "timing.png").is_file()
    assert not (tmp_path / "f" / f"{skipped}.png").exists()
    gif = (tmp_path / "f" / "scene.gif").read_bytes()
    assert gif[:6] in (b"GIF87a", b"GIF89a") and gif.count(b"\x21\xf9\x04") > 5  # frames


def test_a_solves_charged_latency_is_shown_beside_its_wall_time() -> None:
    """sim.latency charged: the timeline says what the plant waited, not only the solver's
    wall time; time paused (latency 0): as before."""
    from hmpc_cli.analysis.replay import _solve, _solves_row

    base = {"t": 0.5, "reason": "period", "status": "Solve_Succeeded", "success": True,
            "iterations": 3, "wall_time": 0.0125, "slack": 0.0}
    assert _solve(base).text == "period: Solve_Succeeded, 3 it, 12.5 ms"
    assert _solve({**base, "latency": 0.0}).text == "period: Solve_Succeeded, 3 it, 12.5 ms"
    assert _solve({**base, "latency": 0.008}).text == \
        "period: Solve_Succeeded, 3 it, 12.5 ms, charged 8.0 ms"
    group = [{**base, "latency": v, "wall_time": w}
             for v, w in ((0.008, 0.010), (0.012, 0.020), (0.006, 0.011))]
    assert _solves_row(group).text == ("... 3 solves ok until t = 0.500 s, 3 iterations "
                                       "median, 11.0 ms median, charged 8.0 ms median "
                                       "(period 3)")
    assert "charged" not in _solves_row([{**g, "latency": 0.0} for g in group]).text
    # a paused first plan (charged nothing) is not in the charged median
    paused = [{**base, "reason": "initial", "latency": 0.0}, {**base, "latency": 0.0425}]
    assert _solves_row(paused).text.endswith(
        "charged 42.5 ms median of 1 charged (initial 1, period 1)")


def test_a_results_page_run_directory_replays_from_its_trajectory_log() -> None:
    """The committed Figure 4 run keeps only its trajectory log (report/trace.mcap):
    replaying the directory reads it."""
    page_run = Path(__file__).resolve().parents[1] / "results" / "biped_stairs" / "report"
    res = replay(page_run)
    assert res.exit_code == 0, res.output
    assert "biped_stairs" in res.output and "trace.mcap" in res.output


def test_a_run_of_ok_solves_says_how_many_stopped_at_the_iteration_limit() -> None:
    """mpc.solver = "rti" logs a solve stopped at its iteration limit at a finite point as
    a success: the summarised row of ok solves counts those (it called them all ok)."""
    from hmpc_cli.analysis.replay import timeline
    from hmpc_cli.log.reader import LogMessage

    def solve(t, status):
        return LogMessage("/mpc/solve", t, {
            "t": t, "reason": "period", "status": status, "success": True,
            "iterations": 1, "wall_time": 0.004, "slack": 0.0, "adopted": True})

    rti = [solve(0.1 * k, "Maximum_Iterations_Exceeded" if k % 3 else "Solve_Succeeded")
           for k in range(6)]
    (row,) = timeline(rti)
    assert row.text == ("... 6 solves ok until t = 0.500 s, 4 at the iteration limit (not "
                        "converged), 1 iterations median, 4.0 ms median (period 6)")
    converged = [solve(0.1 * k, "Solve_Succeeded") for k in range(6)]
    assert timeline(converged)[0].text == ("... 6 solves ok until t = 0.500 s, 1 iterations "
                                           "median, 4.0 ms median (period 6)")


def _log_format_snippet(marker: str) -> str:
    """The Python block of docs/log-format.md that holds ``marker``, unindented."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "log-format.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    (block,) = [b for b in blocks if marker in b]
    return textwrap.dedent(block)


def test_a_killed_runs_log_reads_with_the_mcap_package_as_log_format_says(
        ball, tmp_path, monkeypatch) -> None:
    """log-format.md's StreamReader snippet reads a log cut short (no footer, as SIGKILL
    leaves it) as read_log does, with its run metadata and scenario.toml attachment,
    where make_reader's iter_messages raises."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from hmpc_cli.log.topics import LOG_VERSION, Versions

    whole = (ball / "run.mcap").read_bytes()
    (tmp_path / "run.mcap").write_bytes(whole[:int(len(whole) * 0.6)])
    with open(tmp_path / "run.mcap", "rb") as f, pytest.raises(McapError):
        list(make_reader(f).iter_messages())
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(_log_format_snippet("StreamReader(f, validate_crcs=True)"), scope)
    log = read_log(tmp_path / "run.mcap")
    assert not log.complete and len(log.messages) > 100
    assert sorted((t, lt) for t, lt, _ in scope["messages"]) == sorted(
        (m.topic, m.log_time_ns) for m in [*log.messages, *log.raw])
    info = log.topic("/run/info")[0].data
    assert scope["metadata"] == log.metadata == {"run": {
        "scenario": "ball_disturbed", "seed": "0", "log_version": str(LOG_VERSION),
        **{f"version.{f.name}": info["versions"][f.name]
           for f in dataclasses.fields(Versions)}}}
    assert scope["attachments"] == {"scenario.toml": (ball / "scenario.toml").read_bytes()}
    with open(ball / "run.mcap", "rb") as f:  # the finished log: through its summary
        (att,) = make_reader(f).iter_attachments()
    assert (att.name, att.media_type, att.log_time, att.create_time) == (
        "scenario.toml", "application/toml", 0, 0)


def test_disturbance_statistics_are_those_of_the_window() -> None:
    """Over --from/--to the values in effect there count, each for its time inside: the
    last value of the window was weighted as if it held to the run's end, and a value set
    before --from was left out."""
    from hmpc_cli.analysis.replay import disturbance_stats
    from hmpc_cli.log.reader import LogMessage

    msgs = [LogMessage("/disturbance", t, {"w": {"wx": wx}}) for t, wx in
            ((0.0, 1.0), (0.5, -3.0), (1.0, 5.0))] + [LogMessage("/sim/state", 0.7, {})]

    def stats(*window):
        s = disturbance_stats(msgs, *window)
        return s["values"], s["channels"]["wx"]["max"], s["channels"]["wx"]["mean"]

    assert stats(2.0) == (3, 5.0, pytest.approx(3.5))  # (1 x 0.5 + 3 x 0.5 + 5 x 1) / 2
    assert stats(0.75, 0.25) == (2, 3.0, pytest.approx(2.0))  # 1 then 3, 0.25 s each
    assert stats(1.5, 0.5) == (2, 5.0, pytest.approx(4.0))  # 3 from 0.5, 5 from 1.0
    assert stats(0.4, 0.2) == (1, 1.0, pytest.approx(1.0))  # one value held throughout
    assert disturbance_stats(msgs, 2.0, 100.0)["values"] == 0  # a window past the end
    # a value set at --to holds no time in the window: not counted, nor its max
    assert stats(1.0, 0.5) == (1, 3.0, pytest.approx(3.0))
    assert stats(1.0) == (2, 3.0, pytest.approx(2.0))
    assert stats(1.0, 1.0) == (1, 5.0, pytest.approx(5.0))  # a window of no time


def test_verify_compares_the_run_metadata_record(ball, tmp_path) -> None:
    """The MCAP metadata record's seed edited (0 -> 7, its length kept): --verify said
    identical; it now reports the divergence at t = 0 (exit 1)."""
    data = bytearray((ball / "run.mcap").read_bytes())
    at = _record_at(ball / "run.mcap", 0x0C)
    key = data.index(b"seed", at)
    value = data.index(b"0", key + 4)  # the value's length prefix, then "0"
    data[value:value + 1] = b"7"
    path = tmp_path / "seed7.mcap"
    path.write_bytes(bytes(data))
    assert read_log(path).metadata["run"]["seed"] == "7"
    res = replay(path, "--verify")
    assert res.exit_code == 1, res.output
    assert "diverged at t = 0 s on metadata 'run', field seed: recorded 7, re-run 0" in \
        " ".join(res.output.split()), res.output
    # a key or the record renamed (same length; metadata records have no CRC)
    for old, new, says in ((b"seed", b"sees", "metadata 'run', field sees: recorded 0, "
                                              "re-run (none)"),
                           (b"\x03\x00\x00\x00run", b"\x03\x00\x00\x00rum",
                            "metadata 'rum', field (record): recorded present, re-run "
                            "(none)")):
        data = bytearray((ball / "run.mcap").read_bytes())
        at = data.index(old, _record_at(ball / "run.mcap", 0x0C))
        data[at:at + len(old)] = new
        path.write_bytes(bytes(data))
        res = replay(path, "--verify")
        assert res.exit_code == 1 and f"diverged at t = 0 s on {says}" in \
            " ".join(res.output.split()), res.output


def test_a_scene_cut_before_its_first_state_says_so(ball_log) -> None:
    """A log killed after /scene/static and before the first /scene/body sample: the
    animation's reason is the cut, not 'a system without a drawing, or an older log'."""
    import types

    from hmpc_cli.analysis.tables import FigureInputError
    from hmpc_cli.figures.scene_anim import read_scene

    def cut(complete: bool, damage: str = "", static: bool = True):
        return types.SimpleNamespace(
            complete=complete, damage=damage, raw_topic=lambda topic: (
                ball_log.raw_topic(topic) if topic == "/scene/static" and static else []))

    for log, reason in (
            (cut(False), "the log has no /scene/body sample (the log is cut short)"),
            (cut(False, "bad CRC"), "the log has no /scene/body sample (damaged log: bad CRC)"),
            (cut(True), "the log has no /scene/body sample (it ends before its first state)"),
            (cut(True, static=False), "the log has no /scene/body (a system without a "
                                      "drawing, or a log written before hmpc logged its "
                                      "scene)")):
        with pytest.raises(FigureInputError) as info:
            read_scene(log)
        assert str(info.value) == reason


def test_a_solve_the_model_charged_0_s_counts_as_charged() -> None:
    """sim.latency = "model" charges a 0-iteration solve 0 s: it was charged (the run's
    books count it), so the median and count take it; a paused first plan is not."""
    from hmpc_cli.analysis.replay import _solve, _solves_row, charged_by

    base = {"t": 0.5, "reason": "period", "status": "Solve_Succeeded", "success": True,
            "iterations": 0, "wall_time": 0.0006, "slack": 0.0, "latency": 0.0}
    group = [base, base, {**base, "iterations": 4, "latency": 0.0024}]
    model = charged_by({"latency": "model", "latency_first": "paused"})
    assert _solves_row(group, model).text == (
        "... 3 solves ok until t = 0.500 s, 0 iterations median, 0.6 ms median, charged "
        "0.0 ms median (period 3)")
    assert _solve(base, model).text == "period: Solve_Succeeded, 0 it, 0.6 ms, charged 0.0 ms"
    first = {**base, "reason": "initial"}
    assert _solves_row([first, *group], model).text.endswith(
        "charged 0.0 ms median of 3 charged (initial 1, period 3)")
    paused = charged_by({"latency": "paused"})
    assert "charged" not in _solves_row(group, paused).text
    assert "charged" not in _solve(base, paused).text


def test_verify_forgives_a_version_4_logs_last_sample_in_the_earlier_layout() -> None:
    """Logs of version 4 written before 2026-11-27 end with a /sim/state holding no input
    (u = 0), the state as its reference and a fresh disturbance; since, the last sample
    repeats the last step's. The re-run is compared with them on everything else."""
    from hmpc_cli.analysis.replay import _settings_added_since, compare_logs
    from hmpc_cli.log.reader import LogMessage

    def state(t, u, x_ref, w):
        return LogMessage("/sim/state", t, {"t": t, "x": {"q": 1.0}, "u": {"f": u},
                                            "x_ref": {"q": x_ref}, "w": {"w": w}})

    info = LogMessage("/run/info", 0.0, {"log_version": 4})
    recorded = [info, state(0.0, 5.0, 1.5, 0.1), state(0.1, 0.0, 1.0, 0.7)]
    rerun = [info, state(0.0, 5.0, 1.5, 0.1), state(0.1, 5.0, 1.5, 0.1)]
    assert compare_logs(recorded, rerun) is not None  # as it was: a false divergence
    assert compare_logs(recorded, _settings_added_since(recorded, rerun)) is None
    # a real difference earlier, or a last sample in today's layout, still counts
    moved = [info, state(0.0, 6.0, 1.5, 0.1), state(0.1, 5.0, 1.5, 0.1)]
    assert compare_logs(recorded, _settings_added_since(recorded, moved)) is not None
    today = [info, state(0.0, 5.0, 1.5, 0.1), state(0.1, 5.0, 1.5, 0.2)]
    assert compare_logs(today, _settings_added_since(today, rerun)) is not None
    v6 = LogMessage("/run/info", 0.0, {"log_version": 6})
    assert compare_logs([v6, *recorded[1:]],
                        _settings_added_since([v6, *recorded[1:]], [v6, *rerun[1:]])) \
        is not None
