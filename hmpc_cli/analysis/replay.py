"""Replay of a recorded run: its identity, a timeline, filters and a re-run check.

Plain logic for ``hmpc replay`` (the Typer command is :mod:`hmpc_cli.cli.replay`). The
messages are read as generic JSON dicts: only the names every log version keeps are used
(``t``; ``/sim/event``: ``guard_name``, ``mode_before``, ``mode_after``, ``scheduled``;
``/mpc/solve``: ``reason``, ``status``, ``success``, ``iterations``, ``wall_time``, ``slack``,
``adopted``, ``latency`` (shown when charged); ``/planner/plan``: ``reason``, ``accepted``,
``reached_final``, ``cost``, ``wall_time``, ``note``; ``/disturbance``: ``w``, a list of
numbers or an object of named numbers). The CSV/Parquet export is :mod:`hmpc_cli.analysis.export`.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import math
import re
import statistics
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hmpc_cli.log.topics import FIELDS_ADDED, LOG_VERSION

__all__ = ["LOG_VERSION", "TOPICS", "Divergence", "Replay", "ReplayError", "TimelineRow",
           "compare_logs", "disturbance_stats", "load_replay", "ms_text", "resolve_topics",
           "select", "timeline", "verify"]

#: the topics an hmpc run writes
TOPICS = ("/run/info", "/planner/plan", "/mpc/solve", "/sim/event", "/disturbance",
          "/sim/state", "/run/summary")
SOFTENED_TOL = 1e-6  # as hmpc_cli.log.runlog.SOFTENED_TOL (not imported: it pulls in casadi)
#: the status of a solve stopped at its iteration limit: a success under mpc.solver = "rti"
#: (any finite point) and "sqp_hpipm" (a feasible one), though not converged
ITERATION_LIMIT = "Maximum_Iterations_Exceeded"
RTOL, ATOL = 1e-9, 1e-12
#: the log version from which a scalar field holds its schema's scalar type (4: None, NaN
#: and inf left out instead of null)
TYPED_SCALARS_SINCE = 4
# fields that are measurements or the command line, not results: never compared by verify
_IGNORED = {"wall_time", "versions", "command", "argv", "overrides", "sweep", "log_version",
            "build", "cpu"}
_IGNORED_RE = re.compile(r"(wall_time|_time_(median|mean|p\d+|max|min))$")


class ReplayError(Exception):
    """A log that cannot be replayed or re-run; the message is one line without the file."""


@dataclass
class Replay:
    """A run log read for replay.

    Attributes:
        path: the MCAP file.
        log: the decoded log (:class:`hmpc_cli.log.reader.Log`).
        info: the /run/info payload.
        summary: the /run/summary payload, or None if the run did not finish.
        scenario_text: the attached ``scenario.toml``, or None.
        t_last: time of the last message read [s].
    """

    path: Path
    log: Any
    info: dict
    summary: dict | None
    scenario_text: str | None
    t_last: float

    @property
    def scenario(self) -> dict:
        """The scenario as run (from /run/info), or {}."""
        import json

        text = self.info.get("scenario_json")
        if isinstance(text, str):
            try:
                return dict(json.loads(text))
            except (ValueError, TypeError):
                return {}
        return dict(self.info.get("scenario") or {})

    @property
    def complete(self) -> bool:
        """Whether the file was read to its footer."""
        return bool(self.log.complete)

    @property
    def stopped_at(self) -> float | None:
        """The time [s] a stop signal ended the run at (its summary's ``t_end``), or None."""
        s = self.summary or {}
        reason, t_end = s.get("reason"), s.get("t_end")
        if isinstance(reason, str) and reason.startswith("interrupted") and \
                isinstance(t_end, (int, float)) and not isinstance(t_end, bool):
            return float(t_end)
        return None

    def version_note(self) -> str:
        """A note when the log's version differs from :data:`LOG_VERSION`, else ""."""
        version = self.info.get("log_version", 1)  # logs without it: version 1
        if not isinstance(version, int) or version == LOG_VERSION:
            return ""
        if version < LOG_VERSION:
            return f"written by an older hmpc log version ({version}; this reader: {LOG_VERSION})"
        return f"written by a newer hmpc log version ({version}; this reader: {LOG_VERSION})"


@dataclass
class TimelineRow:
    """One timeline line: time, kind (contact, plan, solve, solves, ...), text, emphasis."""

    t: float
    kind: str
    text: str
    style: str = ""


@dataclass
class Divergence:
    """The first difference between a log and its re-run."""

    t: float
    topic: str
    path: str
    recorded: Any
    rerun: Any


def resolve_log_path(path: Path) -> Path:
    """The MCAP file of ``path``: a file, or a run directory's ``run.mcap``.

    A directory without one gives the trajectory log a results page keeps there
    (``trace.mcap``) if it has one.

    Raises:
        ReplayError: missing, a directory without either log, or an empty file.
    """
    from hmpc_cli.log.rundata import sweep_text
    from hmpc_cli.log.trace import TRACE_NAME

    if path.is_dir():
        found = [path / name for name in ("run.mcap", TRACE_NAME) if (path / name).is_file()]
        if not found:
            raise ReplayError(f"a directory without run.mcap (or {TRACE_NAME})"
                              + sweep_text(path))
        path = found[0]
    if not path.exists():
        raise ReplayError("no such file")
    if not path.is_file():
        raise ReplayError("not a regular file")
    if path.stat().st_size == 0:
        raise ReplayError("empty file: the run was stopped before anything was logged")
    return path


def _no_message(path: Path, log) -> None:
    """Why a log holds no JSON message (a :class:`ReplayError`, always raised)."""
    if log.damage:
        raise ReplayError(f"damaged log: no message could be read: {log.damage}")
    raw = sorted({m.topic for m in log.raw})
    if raw and not all(t.startswith("/scene/") for t in raw):
        raise ReplayError(f"not an hmpc run log (no /run/info; its topics: {', '.join(raw)})")
    if raw:  # hmpc's scene, written before the run's first message
        raise ReplayError("no /run/info: the run stopped before it logged anything but its "
                          f"scene ({', '.join(raw)})")
    held = "its header" + "".join(f" and attachment {n!r}" for n in sorted(log.attachments))
    raise ReplayError("no message could be read: the run was stopped before anything was "
                      f"logged ({path.stat().st_size} bytes: "
                      + ("closed with no message)" if log.complete else
                         f"{held} only), or the file was cut short after them"))


def load_replay(path: Path) -> Replay:
    """Reads a run log for replay; a truncated or damaged file yields what was completed.

    Raises:
        ReplayError: not an MCAP file, another program's MCAP file, or nothing readable.
    """
    from hmpc_cli.log.reader import read_log

    path = resolve_log_path(path)
    try:
        log = read_log(path)
    except ValueError as exc:
        if "not an MCAP file" in str(exc):
            raise ReplayError("not an MCAP file") from None
        raise ReplayError(f"unreadable MCAP file ({exc})") from None
    except OSError as exc:
        raise ReplayError(f"cannot read ({exc.strerror or exc})") from None
    if not log.messages:
        _no_message(path, log)
    infos = log.topic("/run/info")
    if not infos and log.damage:  # its first chunk, which holds /run/info, is lost
        raise ReplayError(f"damaged log: its /run/info could not be read: {log.damage}")
    if not infos:
        topics = sorted({m.topic for m in log.messages})
        raise ReplayError("not an hmpc run log (no /run/info; its topics: "
                          f"{', '.join(topics)})")
    if not isinstance(infos[0].data, dict) or "scenario_name" not in infos[0].data:
        raise ReplayError("not an hmpc run log (its /run/info has no scenario_name)")
    version = infos[0].data.get("log_version")
    problem = mistyped(log.messages, version if isinstance(version, int)
                       and not isinstance(version, bool) else 1)  # none: version 1
    if problem is not None:
        raise ReplayError(f"damaged log: its content cannot be read: {problem}")
    summaries = log.topic("/run/summary")
    text = log.attachments.get("scenario.toml")
    try:
        text = text.decode("utf-8") if text is not None else None
    except (UnicodeDecodeError, AttributeError):
        text = None
    return Replay(path, log, infos[0].data, summaries[-1].data if summaries else None, text,
                  max(m.t for m in log.messages))


_KINDS = {"object": (dict,), "array": (list,), "number": (int, float), "integer": (int,),
          "string": (str,), "boolean": (bool,)}


def _kind_problem(schema: dict, value: Any, version: int = LOG_VERSION) -> str | None:
    """Why ``value`` is not of the JSON kind ``schema`` says (None: it is, or null).

    ``version``: the log's layout. Before :data:`TYPED_SCALARS_SINCE` any scalar passes
    where the schema says a scalar; in version 1 (plain arrays, untyped) also an array
    where it says an object: only a scalar against an object or array is told apart there.
    """
    kind = schema["type"]
    if value is None:  # left out or non-finite: not a type error of its own
        return None
    if isinstance(value, _KINDS[kind]) and not (kind in ("number", "integer")
                                                and isinstance(value, bool)):
        return None
    container = isinstance(value, (dict, list))
    if version < TYPED_SCALARS_SINCE and kind not in ("object", "array") and not container:
        return None
    if version < 2 and kind in ("object", "array") and container:
        return None
    return f"expected {'an' if kind[0] in 'aeiou' else 'a'} {kind}, got {_json_kind(value)}"


def _json_kind(value: Any) -> str:
    return {dict: "an object", list: "an array", str: "a string", bool: "a boolean"}.get(
        type(value), "a number")


@functools.cache
def _top_schemas() -> dict[str, dict]:
    """The schemas of hmpc's topics without the run's names: their fixed fields' kinds."""
    from hmpc_cli.log.schema import type_schema
    from hmpc_cli.log.topics import TOPICS

    return {topic: type_schema(cls, {}, {})["properties"] for topic, (_, cls) in TOPICS.items()}


def mistyped(messages: list, version: int = LOG_VERSION) -> str | None:
    """The first field of hmpc's topics whose JSON kind is not its schema's, in words.

    Checks each message's own fields and the items of its arrays (not the fields named
    after the run's states, inputs and guards, which need the run's names), as far as
    the log's layout ``version`` fixes them (:func:`_kind_problem`). None: every kind
    fits, which is what the timeline, tables and export read as generic JSON.
    """
    schemas = _top_schemas()
    for m in messages:
        props = schemas.get(m.topic)
        if props is None or not isinstance(m.data, dict):
            continue
        for key, sub in props.items():
            value = m.data.get(key)
            why = _kind_problem(sub, value, version)
            if why is None and sub["type"] == "array" and isinstance(value, list):
                why = next((w for v in value
                            if (w := _kind_problem(sub["items"], v, version))), None)
                key += "[]"
            if why is not None:
                return f"{m.topic} at t = {m.t:.6g} s: {key}: {why}"
    return None


def guarded(path: Path, what: str = ""):
    """A guard that reports wrongly typed content of the log at ``path`` as damage.

    (:func:`hmpc_cli.log.damage.reading`): the timeline, tables, export and comparison
    read the messages as generic JSON; a foreign or damaged log's odd types end there.
    """
    from hmpc_cli.log.damage import reading

    return reading(path, what)


def resolve_topics(names: list[str], present: list[str], scene: list[str] = ()) -> list[str]:
    """Full topic names for ``--topic`` values.

    A value is a full name (``/mpc/solve``), the name without its slash (``mpc/solve``) or
    its last part when that is unique (``solve``, ``event``, ``plan``, ``state``, ...).
    ``scene`` are the log's undecoded (protobuf) topics, which are not filtered.

    Raises:
        ReplayError: an unknown topic (the message lists the known ones), or a scene topic.
    """
    known = list(TOPICS) + sorted(set(present) - set(TOPICS))
    out: list[str] = []
    for name in names:
        key = name.strip().strip("/")
        hits = [t for t in known if t.strip("/") == key] or \
               [t for t in known if t.rsplit("/", 1)[-1] == key]
        if not hits and key in {t.strip("/") for t in scene}:
            raise ReplayError(f"{name!r} is a 3D-scene topic (protobuf, for Foxglove or "
                              f"Lichtblick): --topic selects the JSON topics "
                              f"({', '.join(known)})")
        if len(hits) != 1:
            raise ReplayError(f"unknown topic {name!r} (known: {', '.join(known)})")
        if hits[0] not in out:
            out.append(hits[0])
    return out


def select(messages: list, t0: float | None = None, t1: float | None = None,
           topics: list[str] | None = None) -> list:
    """Messages with ``t0 <= t <= t1`` (either bound optional) on ``topics`` (all if None)."""
    keep = set(topics) if topics else None
    return [m for m in messages
            if (keep is None or m.topic in keep)
            and (t0 is None or m.t >= t0 - 1e-12) and (t1 is None or m.t <= t1 + 1e-12)]


def _num(v: Any) -> float | None:
    """``v`` as a finite float, or None."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return None
    return float(v)


def ms_text(v: Any) -> str:
    """Seconds as milliseconds text ('12.3 ms'), or '-' (none, not finite)."""
    v = _num(v)
    return "-" if v is None else f"{1e3 * v:.1f} ms"


def _g(v: Any) -> str:
    """A number in 4 significant digits, or '-'."""
    v = _num(v)
    return "-" if v is None else f"{v:.4g}"


def _contact(d: dict) -> TimelineRow:
    """Timeline row of a /sim/event message."""
    sched = "scheduled" if d.get("scheduled") else "NOT scheduled"
    text = (f"{d.get('guard_name', '?')}: {d.get('mode_before', '?')} -> "
            f"{d.get('mode_after', '?')} ({sched})")
    return TimelineRow(float(d.get("t", 0.0)), "contact", text,
                       "" if d.get("scheduled") else "yellow")


def _plan(d: dict) -> TimelineRow:
    """Timeline row of a /planner/plan message."""
    acc = "accepted" if d.get("accepted") else "REJECTED"
    text = f"{d.get('reason', '?')}: {acc}, cost {_g(d.get('cost'))}, {ms_text(d.get('wall_time'))}"
    if d.get("reached_final") is False:
        text += ", did not reach the final domain"
    if d.get("note"):
        text += f"; {d['note']}"
    return TimelineRow(float(d.get("t", 0.0)), "plan", text, "" if d.get("accepted") else "red")


def _ordinary(d: dict) -> bool:
    """A successful, adopted, not softened solve."""
    slack = _num(d.get("slack")) or 0.0
    return bool(d.get("success")) and slack <= SOFTENED_TOL and d.get("adopted", True) is not False


def _solve(d: dict, is_charged: Callable[[dict], bool] | None = None) -> TimelineRow:
    """Timeline row of one /mpc/solve message (``is_charged``: :func:`charged_by`)."""
    ok = bool(d.get("success"))
    text = (f"{d.get('reason', '?')}: {'' if ok else 'FAILED '}{d.get('status', '?')}, "
            f"{d.get('iterations', '?')} it, {ms_text(d.get('wall_time'))}")
    if (is_charged or charged_by(None))(d) and _num(d.get("latency")) is not None:
        text += f", charged {ms_text(d.get('latency'))}"  # what the plant waited
    style = "" if ok else "bold red"
    slack = _num(d.get("slack")) or 0.0
    if ok and slack > SOFTENED_TOL:
        text += f", softened (slack {slack:.3g})"
        style = "yellow"
    if d.get("adopted") is False:
        text += ", not adopted"
        style = style or "yellow"
    return TimelineRow(float(d.get("t", 0.0)), "solve", text, style)


def charged_by(sim: dict | None) -> Callable[[dict], bool]:
    """Whether an /mpc/solve was charged, from the run's ``sim`` settings (None: unknown).

    Every solve of a run with compute time charged (``sim.latency`` not "paused"),
    but the first plan's with ``sim.latency_first = "paused"``, as the run's books count
    them: a solve charged 0 s (a model's 0 iterations) was charged. Without the
    settings, a solve that was charged more than nothing.
    """
    if sim is None:
        return lambda d: bool(_num(d.get("latency")))
    kind, first = sim.get("latency", "paused"), sim.get("latency_first", "charged")
    if kind == "paused":
        return lambda d: False
    return lambda d: not (first == "paused" and str(d.get("reason", "")).startswith("initial"))


def _solves_row(group: list[dict],
                is_charged: Callable[[dict], bool] | None = None) -> TimelineRow:
    """One row for a run of ordinary solves (a single one is shown as it is).

    It says how many of them stopped unconverged at the iteration limit (successes of a
    bounded SQP run, e.g. ``mpc.solver = "rti"``).
    """
    if len(group) == 1:
        return _solve(group[0], is_charged)
    limit = sum(d.get("status") == ITERATION_LIMIT for d in group)
    its = [v for v in (_num(d.get("iterations")) for d in group) if v is not None]
    wall = [v for v in (_num(d.get("wall_time")) for d in group) if v is not None]
    is_charged = is_charged or charged_by(None)
    charged = [v for v in (_num(d.get("latency")) for d in group if is_charged(d))
               if v is not None]
    reasons: dict[str, int] = {}
    for d in group:
        reasons[str(d.get("reason", "?"))] = reasons.get(str(d.get("reason", "?")), 0) + 1
    text = (f"... {len(group)} solves ok until t = {float(group[-1].get('t', 0.0)):.3f} s, "
            + (f"{limit} at the iteration limit (not converged), " if limit else "")
            + f"{_g(statistics.median(its)) if its else '-'} iterations median, "
            f"{ms_text(statistics.median(wall)) if wall else '-'} median"
            + (f", charged {ms_text(statistics.median(charged))} median"
               + (f" of {len(charged)} charged" if len(charged) < len(group) else "")
               if charged else "")
            + " (" + ", ".join(f"{k} {n}" for k, n in reasons.items()) + ")")
    return TimelineRow(float(group[0].get("t", 0.0)), "solves", text, "dim")


def timeline(messages: list, show_all: bool = False,
             is_charged: Callable[[dict], bool] | None = None) -> list[TimelineRow]:
    """The time-ordered timeline of contacts, planner calls and solves.

    Args:
        messages: log messages (any topics; only events, plans and solves appear).
        show_all: one row per solve; otherwise runs of ordinary solves (successful,
            adopted, not softened) between other rows are summarised in one row.
        is_charged: whether a solve was charged (:func:`charged_by`; None: one charged
            more than nothing).
    """
    is_charged = is_charged or charged_by(None)
    rank = {"/sim/event": 0, "/planner/plan": 1, "/mpc/solve": 2}  # contact, then replan
    ordered = sorted((m for m in messages if m.topic in rank),
                     key=lambda m: (m.t, rank[m.topic]))
    rows: list[TimelineRow] = []
    group: list[dict] = []
    for m in ordered:
        if m.topic == "/mpc/solve" and not show_all and _ordinary(m.data):
            group.append(m.data)
            continue
        if group:
            rows.append(_solves_row(group, is_charged))
            group = []
        if m.topic == "/mpc/solve":
            rows.append(_solve(m.data, is_charged))
        else:
            rows.append({"/planner/plan": _plan, "/sim/event": _contact}[m.topic](m.data))
    if group:
        rows.append(_solves_row(group, is_charged))
    return rows


def _channels(w: Any) -> dict[str, float]:
    """Named channels of one disturbance value (a list or an object of numbers)."""
    if isinstance(w, dict):
        return {str(k): abs(_num(v) or 0.0) for k, v in w.items()}
    if isinstance(w, (list, tuple)):
        return {f"w[{i}]": abs(_num(v) or 0.0) for i, v in enumerate(w)}
    v = _num(w)
    return {} if v is None else {"w": abs(v)}


def disturbance_stats(messages: list, t_end: float, t_start: float | None = None) -> dict:
    """Statistics of the /disturbance values in effect over [t_start, t_end] [s].

    Each value holds until the next one (the last until ``t_end``); a value set before
    ``t_start`` counts from ``t_start`` (None: from the first value). A value that holds no
    time in the window (set at ``t_end``) is not counted. The mean |w| is time-weighted (a
    plain mean of every value if the values span no time).

    Returns:
        ``{"values": N, "changes": N - 1, "channels": {name: {"max": .., "mean": ..}}}``.
    """
    dist = sorted((m for m in messages if m.topic == "/disturbance"), key=lambda m: m.t)
    lo = -math.inf if t_start is None else t_start
    if lo > t_end:  # a window after the run's end: no value held in it
        return {"values": 0, "changes": 0, "channels": {}}
    held = [m for m in dist if m.t <= lo + 1e-12]  # the value in effect at t_start
    dist = held[-1:] + [m for m in dist if lo + 1e-12 < m.t <= t_end + 1e-12]
    if not dist:
        return {"values": 0, "changes": 0, "channels": {}}
    starts = [max(m.t, lo) for m in dist]
    ends = starts[1:] + [max(t_end, starts[-1])]
    spans = [max(e - t, 0.0) for t, e in zip(starts, ends, strict=True)]
    total = sum(spans)
    if total > 0:  # a value set at the window's end held no time in it: not counted
        dist, spans = zip(*((m, s) for m, s in zip(dist, spans, strict=True) if s > 0),
                          strict=True)
    weights = [s / total for s in spans] if total > 0 else [1 / len(dist)] * len(dist)
    chans: dict[str, dict[str, float]] = {}
    for m, wgt in zip(dist, weights, strict=True):
        for name, a in _channels(m.data.get("w")).items():
            c = chans.setdefault(name, {"max": 0.0, "mean": 0.0})
            c["max"] = max(c["max"], a)
            c["mean"] += wgt * a
    return {"values": len(dist), "changes": len(dist) - 1, "channels": chans}


def _ignored(key: str) -> bool:
    """Whether a field is a measurement, the machine or the command line (skipped by verify)."""
    return key in _IGNORED or bool(_IGNORED_RE.search(key))


def _differs(a: Any, b: Any) -> bool:
    """Whether two JSON leaves differ (numbers to RTOL/ATOL)."""
    na, nb = _num(a), _num(b)
    if na is not None and nb is not None:
        return abs(na - nb) > max(ATOL, RTOL * max(abs(na), abs(nb)))
    return type(a) is not type(b) or a != b


def first_difference(a: Any, b: Any, path: str = "") -> tuple[str, Any, Any] | None:
    """The first differing field of two JSON values: (path, value in a, value in b).

    A key whose value is null counts as absent (logs before version 4 wrote null where
    later ones leave the key out).
    """
    if isinstance(a, dict) and isinstance(b, dict):
        a = {k: v for k, v in a.items() if v is not None}
        b = {k: v for k, v in b.items() if v is not None}
        for key in list(a) + [k for k in b if k not in a]:
            if _ignored(str(key)):
                continue
            sub = f"{path}.{key}" if path else str(key)
            if key not in b or key not in a:
                return sub, a.get(key, "(missing)"), b.get(key, "(missing)")
            hit = first_difference(a[key], b[key], sub)
            if hit:
                return hit
        return None
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{path} (length)", len(a), len(b)
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            hit = first_difference(x, y, f"{path}[{i}]")
            if hit:
                return hit
        return None
    return (path or "(value)", a, b) if _differs(a, b) else None


def _topic_divergence(topic: str, rec: list, new: list, prefix_only: bool) -> Divergence | None:
    """The first divergence on one topic (message by message), or None."""
    for i, m in enumerate(rec):
        if i >= len(new):
            return Divergence(m.t, topic, "(message count)", len(rec), len(new))
        hit = first_difference(m.data, new[i].data)
        if hit:
            return Divergence(m.t, topic, *hit)
    if len(new) > len(rec) and not prefix_only:
        m = new[len(rec)]
        return Divergence(m.t, topic, "(message count)", len(rec), len(new))
    return None


def compare_logs(recorded: list, rerun: list, prefix_only: bool = False) -> Divergence | None:
    """The first divergence between two logs' messages, or None if they agree.

    Topics are compared message by message (count, keys, values; numbers to a relative
    1e-9, measured times and the command line skipped); of the per-topic divergences the
    earliest is returned. /run/info counts only when nothing else diverges: it holds the
    inputs (the scenario), not the behaviour, so an edited scenario is reported where the
    run first behaves differently.

    Args:
        recorded: the recorded log's messages.
        rerun: the re-run's messages.
        prefix_only: the recorded log was cut short: extra re-run messages are fine.
    """
    order = {t: i for i, t in enumerate(TOPICS[1:] + TOPICS[:1])}
    topics = sorted({m.topic for m in recorded} | {m.topic for m in rerun},
                    key=lambda t: (order.get(t, len(order)), t))
    found = []
    for topic in topics:
        div = _topic_divergence(topic, [m for m in recorded if m.topic == topic],
                                [m for m in rerun if m.topic == topic], prefix_only)
        if div is not None:
            found.append((topic == "/run/info", div.t, order.get(topic, len(order)), div))
    return min(found, key=lambda f: f[:3])[3] if found else None


def unverifiable(replay: Replay) -> str | None:
    """Why no re-run can be compared with the log (one line), or None.

    A damaged log misses messages, or the scenario or record a re-run is checked
    against; a run that charged its measured compute time (``sim.latency = "measured"``)
    diverges from any re-run by design.
    """
    if replay.log.damage:
        return (f"damaged log ({replay.log.damage}): what a re-run would be compared with "
                f"is not all there, so no re-run can be compared with it (hmpc replay shows "
                f"what it holds intact)")
    sim = replay.scenario.get("sim")
    if isinstance(sim, dict) and sim.get("latency") == "measured":
        return ('the run charged its measured compute time (sim.latency = "measured"): a '
                "re-run charges this machine's times now, its plans reach the plant at "
                "other moments and it diverges by design; --verify re-runs runs with time "
                'paused, a fixed latency or sim.latency = "model"')
    return None


def verify(replay: Replay, workdir: Path) -> tuple[Divergence | None, int, int]:
    """Re-runs the log's attached scenario (its seed) in ``workdir`` and compares the logs.

    A log cut short, or of a run a stop signal ended, is compared up to where it ends (a
    stopped run's summary and its last state sample, written at the stop, left out).

    Returns:
        The first divergence (or None), the number of compared messages and of topics.

    Raises:
        ReplayError: no scenario attached, the scenario cannot be rebuilt, or
            :func:`unverifiable`.
    """
    from hmpc_cli.log.reader import read_log
    from hmpc_cli.core.registry import PluginError
    from hmpc_cli.run.runner import prepare, execute_run
    from hmpc_cli.run.scenario import ScenarioError, load_scenario

    if not replay.scenario_text:
        raise ReplayError("no scenario.toml attached: the run cannot be re-run")
    why = unverifiable(replay)
    if why is not None:
        raise ReplayError(why)
    toml = workdir / "scenario.toml"
    toml.write_text(replay.scenario_text, encoding="utf-8")
    try:
        sc, text = load_scenario(toml)
        prepared = prepare(sc)
    except ScenarioError as exc:
        detail = "; ".join(line.replace(str(toml), "scenario.toml") for line in exc.lines)
        raise ReplayError(f"the attached scenario cannot be rebuilt: {detail}") from None
    except (PluginError, ValueError, RuntimeError) as exc:
        raise ReplayError(f"the attached scenario cannot be rebuilt: {exc}") from None
    execute_run(prepared, text, workdir / "rerun")
    again = read_log(workdir / "rerun" / "run.mcap")
    recorded, stop = replay.log.messages, replay.stopped_at
    if stop is not None:  # what the stop wrote, which no re-run writes there
        recorded = [m for m in recorded if m.topic != "/run/summary"
                    and not (m.topic == "/sim/state" and m.t >= stop - 1e-6)]  # ns log times
    prefix = not replay.complete or stop is not None
    with guarded(replay.path, "comparing it with the re-run"):
        rerun = _settings_added_since(recorded, again.messages)
        found = [compare_logs(recorded, rerun, prefix_only=prefix)]
        if replay.log.raw:  # a log written without its 3D scene (run_to_log) has none
            found.append(scene_divergence(replay.log.raw, again.raw, prefix_only=prefix))
        found.append(metadata_divergence(replay.log.metadata, again.metadata))
    found = [d for d in found if d is not None]
    div = min(found, key=lambda d: d.t) if found else None
    n = len(recorded) + len(replay.log.raw)
    return div, n, len({m.topic for m in recorded} | {m.topic for m in replay.log.raw})


def metadata_divergence(recorded: dict, rerun: dict) -> Divergence | None:
    """The first difference of the MCAP metadata records (scenario name, seed), or None.

    Reported at t = 0: a record or key the recorded log holds and the re-run not
    ("(none)"), or a value that differs; what only the re-run holds counts as added
    since the recorded run; versions and skipped fields (:func:`_ignored`) left out.
    """
    for name in sorted(recorded):
        was, now = recorded[name], rerun.get(name)
        if now is None:
            return Divergence(0.0, f"metadata {name!r}", "(record)", "present", "(none)")
        for key in sorted(was):
            if key.startswith("version.") or _ignored(key):
                continue
            if was[key] != now.get(key, "(none)"):
                return Divergence(0.0, f"metadata {name!r}", key, was[key],
                                  now.get(key, "(none)"))
    return None


def scene_divergence(recorded: list, rerun: list, prefix_only: bool = False
                     ) -> Divergence | None:
    """The earliest divergence of the undecoded (3D-scene, protobuf) messages, or None.

    Topic by topic, message by message: the count, the time and the encoded bytes (the
    scene is drawn from the logged states, so a re-run writes the same bytes).
    """
    found = []
    for topic in sorted({m.topic for m in recorded} | {m.topic for m in rerun}):
        rec = [m for m in recorded if m.topic == topic]
        new = [m for m in rerun if m.topic == topic]
        for m, n in zip(rec, new, strict=False):
            if m.t != n.t or m.data != n.data:
                found.append(Divergence(m.t, topic, "(protobuf message)",
                                        f"{len(m.data)} bytes at t = {m.t:.6g} s",
                                        f"{len(n.data)} bytes at t = {n.t:.6g} s"))
                break
        else:
            if len(rec) > len(new) or (len(new) > len(rec) and not prefix_only):
                at = (rec if len(rec) > len(new) else new)[min(len(rec), len(new))]
                found.append(Divergence(at.t, topic, "(message count)", len(rec), len(new)))
    return min(found, key=lambda d: d.t) if found else None


def _old_final_sample(recorded: list, rerun: list) -> list:
    """The re-run's messages, its last /sim/state's u, x_ref and w as an old log's.

    When the recorded last sample is in the layout before 2026-11-27 (log version 4
    then and after): that last sample held no input (u = 0), the state as its own reference and a
    disturbance drawn after the last step; since, it repeats the last step's values. A
    recorded log of that layout (u all 0, x_ref = x) is compared on the rest.
    """
    rec = [m for m in recorded if m.topic == "/sim/state"]
    new = [i for i, m in enumerate(rerun) if m.topic == "/sim/state"]
    if not rec or not new or not isinstance(rec[-1].data, dict):
        return rerun
    last = rec[-1].data
    u, x, x_ref = last.get("u"), last.get("x"), last.get("x_ref")
    if not (isinstance(u, dict) and all(v == 0 for v in u.values()) and x_ref == x):
        return rerun
    i = new[-1]
    if not isinstance(rerun[i].data, dict):
        return rerun
    fixed = {**rerun[i].data, **{k: last[k] for k in ("u", "x_ref", "w") if k in last}}
    return [*rerun[:i], dataclasses.replace(rerun[i], data=fixed), *rerun[i + 1:]]


def _settings_added_since(recorded: list, rerun: list) -> list:
    """The re-run's messages, the settings and fields added since the recorded run forgiven.

    A setting the recorded /run/info scenario lacks took its default in the re-run (as a
    sweep's resume treats it): when the re-run's scenario equals the recorded one but for
    such keys, it is taken as the recorded one. A message field a later log version added
    (:data:`~hmpc_cli.log.topics.FIELDS_ADDED`) is left out of the re-run's messages when
    the recorded log is older, and a version-4 log's last /sim/state in the earlier layout
    is compared without its u, x_ref and w (:func:`_old_final_sample`). Every behaviour
    still counts.
    """
    info = next((m for m in recorded if m.topic == "/run/info"), None)
    version = info.data.get("log_version", 1) if info is not None else LOG_VERSION
    added: dict[str, set[str]] = {}
    for (topic, name), since in FIELDS_ADDED.items():
        if not isinstance(version, int) or version < since:
            added.setdefault(topic, set()).add(name)
    rerun = [dataclasses.replace(m, data={k: v for k, v in m.data.items()
                                          if k not in added[m.topic]})
             if m.topic in added and isinstance(m.data, dict) else m for m in rerun]
    if isinstance(version, int) and version <= 4:
        rerun = _old_final_sample(recorded, rerun)
    try:
        old = json.loads(info.data["scenario_json"]) if info is not None else None
    except (KeyError, TypeError, ValueError):
        return rerun

    def known(new, was):
        if isinstance(new, dict) and isinstance(was, dict):
            return {k: known(v, was[k]) for k, v in new.items() if k in was}
        return new

    out = []
    for m in rerun:
        if m.topic == "/run/info" and isinstance(old, dict):
            try:
                same = known(json.loads(m.data["scenario_json"]), old) == old
            except (KeyError, TypeError, ValueError):
                same = False
            if same:
                m = dataclasses.replace(m, data={**m.data,
                                                 "scenario_json": info.data["scenario_json"]})
        out.append(m)
    return out
