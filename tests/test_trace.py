"""A run's trajectory log (trace.mcap): the page's topics copied unchanged, read like a run
log, found where the run log is not, refused cleanly when the source is not a log."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from hmpc_cli.analysis.tables import resolve_log as resolve_table_log
from hmpc_cli.analysis.tables import resolve_run_log
from hmpc_cli.log.reader import read_log
from hmpc_cli.log.rundata import read_run
from hmpc_cli.log.trace import TRACE_NAME, TRACE_TOPICS, period_shifts, write_trace

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def traced(full_run, tmp_path_factory):
    """The default ball run's log and its trajectory log, in a directory of their own."""
    assert full_run.proc.returncode == 0, full_run.proc.stderr
    d = tmp_path_factory.mktemp("trace") / "run"
    d.mkdir()
    shutil.copy(full_run.out / "run.mcap", d / "run.mcap")
    return d / "run.mcap", write_trace(d / "run.mcap")


def test_the_trace_keeps_its_topics_message_for_message(traced):
    log, trace = traced
    assert trace == log.with_name(TRACE_NAME) and not list(trace.parent.glob(".*tmp"))
    full, kept = read_log(log), read_log(trace)
    assert kept.complete and not kept.damage
    assert {m.topic for m in kept.messages} == set(TRACE_TOPICS)
    want = [(m.topic, m.t, m.data) for m in full.messages if m.topic in TRACE_TOPICS]
    assert [(m.topic, m.t, m.data) for m in kept.messages] == want
    assert kept.schemas == {t: s for t, s in full.schemas.items() if t in TRACE_TOPICS}
    assert trace.stat().st_size < log.stat().st_size / 5


def test_the_traces_summary_names_its_channels_for_an_indexed_reader(traced):
    """A viewer (Lichtblick, Foxglove) lists a file's topics from its summary section: the
    trace repeats its schemas and channels there, and reads through its index (the
    committed traces too)."""
    from mcap.reader import make_reader

    from hmpc_cli.log.reader import _read_indexed

    _, trace = traced
    committed = sorted((ROOT / "results" / "sweeps").glob("*/runs/*/" + TRACE_NAME))
    assert len(committed) > 100
    for path in (trace, *committed):
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        channels = summary.channels.values()
        assert {c.topic for c in channels} <= set(TRACE_TOPICS), path
        assert {c.schema_id for c in channels} <= set(summary.schemas), path
        assert summary.statistics.channel_count == len(summary.channels) > 0, path
    assert len(_read_indexed(trace).messages) == len(read_log(trace).messages)


def test_the_trace_reads_back_as_the_run_did(traced):
    log, trace = traced
    a, b = read_run(log), read_run(trace)
    assert np.array_equal(a.t, b.t) and np.array_equal(a.x, b.x, equal_nan=True)
    assert [(e.t, e.guard_name, *e.x_before, *e.x_after) for e in a.events] == \
        [(e.t, e.guard_name, *e.x_before, *e.x_after) for e in b.events] != []
    assert a.summary == b.summary and a.geometry == b.geometry and a.scenario == b.scenario
    assert [(p.t, p.accepted) for p in a.planner] == [(p.t, p.accepted) for p in b.planner]
    assert a.solves != [] and b.solves == []


def test_the_trace_keeps_the_node_shift_of_every_periodic_re_solve(traced):
    log, trace = traced
    want = tuple(s.detail.shifted for s in read_run(log).solves if s.reason == "period")
    assert period_shifts(trace) == want and len(want) > 20
    assert period_shifts(log) == ()  # a run log has its /mpc/solve instead


def test_a_missing_run_log_is_read_from_its_trace(traced, tmp_path):
    _, trace = traced
    d = tmp_path / "runs" / "r1"
    d.mkdir(parents=True)
    shutil.copy(trace, d / TRACE_NAME)
    assert resolve_run_log(d) == d / TRACE_NAME
    assert resolve_run_log(d / "run.mcap") == d / TRACE_NAME
    assert resolve_table_log(tmp_path / "results.csv", "runs/r1/run.mcap", "t") == d / TRACE_NAME
    assert read_run(d).summary is not None
    (d / "run.mcap").write_bytes(trace.read_bytes())  # a run log there is read first
    assert resolve_run_log(d) == d / "run.mcap"


def test_a_source_that_is_not_a_log_is_refused_and_nothing_is_left(tmp_path):
    bad = tmp_path / "run.mcap"
    bad.write_bytes(b"not an mcap file at all")
    with pytest.raises(ValueError, match="cannot copy its trajectory"):
        write_trace(bad)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap"]
