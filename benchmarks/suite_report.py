"""The benchmark suite's table, profile, targets and machine description (text, Markdown, CSV).

Times in the table are wall times per solve [ms]; ratios are of medians.
"""

from __future__ import annotations

import csv
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
from dataclasses import asdict, dataclass
from importlib import metadata

import numpy as np

#: configuration label -> what it is (the report's legend)
LEGEND = {
    "authors": "rebuild the NLP + cold IPOPT, default options, every call (the reference code)",
    "ipopt_defaults": "IPOPT with CasADi's default options, cold, same primal guess",
    "hmpc_ipopt": "hmpc's IPOPT: warm instance, primal-dual warm start (the default)",
    "sqp_hpipm_rti1": "SQP + Gauss-Newton + HPIPM, 1 iteration (IPOPT fallback)",
    "sqp_hpipm_rti3": "SQP + Gauss-Newton + HPIPM, 3 iterations (hmpc's default for it)",
    "sqp_hpipm_conv": "SQP + Gauss-Newton + HPIPM, converged (50 iterations)",
    "fatrop": "fatrop, stage structure detected, cold (no dual warm start via CasADi)",
    "rti": "real-time iterations (mpc.solver = \"rti\"): one SQP step from the warm start, "
           "kept, no fallback (not a converged solve: the closed loop's next steps go on)",
    "do_mpc": "do-mpc default MPC (orthogonal collocation), final-domain problem only",
}
#: hmpc's own back-ends (the fastest one is profiled)
HMPC = ("hmpc_ipopt", "sqp_hpipm_rti1", "sqp_hpipm_rti3", "sqp_hpipm_conv", "fatrop", "rti")
NLPS = ("final", "switching", "all")
MS = 1e3
#: the parts of one solve call (see :func:`profile`)
PARTS = ("QP solve (HPIPM via CasADi)", "function evaluations (nlp_*)",
         "line search (net of its nlp_fg)",
         "rest of the solver (IPOPT: linear algebra; SQP: steps)",
         "the buffered call around the solver", "hmpc's Python around the call")


@dataclass(frozen=True)
class Row:
    """One configuration on one NLP ("all": both).

    Attributes:
        nlp: "final", "switching" or "all".
        config: configuration label (see :data:`LEGEND`).
        solves: problems solved.
        median_ms, p95_ms, max_ms: wall time per solve [ms].
        mean_iter: mean solver iterations.
        failures: solves that did not succeed (after any fallback).
        fallbacks: solves a back-end failed and IPOPT solved instead.
        vs_hmpc: median / hmpc_ipopt's median (< 1: faster).
        authors_x: authors' median / this median (how many times faster than the authors).
        dompc_x: do-mpc's median / this median (final NLP only, else NaN).
    """

    nlp: str
    config: str
    solves: int
    median_ms: float
    p95_ms: float
    max_ms: float
    mean_iter: float
    failures: int
    fallbacks: int
    vs_hmpc: float
    authors_x: float
    dompc_x: float


def rows(stats: dict) -> list[Row]:
    """Table rows per NLP and configuration from ``{(config, nlp): [SolveStats]}``."""
    out = []
    order = {k: i for i, k in enumerate(LEGEND)}
    for nlp in NLPS:
        by = {}
        for (label, nl), st in sorted(stats.items(), key=lambda kv: order.get(kv[0][0], 99)):
            if nl == nlp or (nlp == "all" and label != "do_mpc"):
                by.setdefault(label, []).extend(st)
        med = {k: float(np.median([s.wall_time for s in v])) for k, v in by.items() if v}
        for label, st in by.items():
            t = MS * np.array([s.wall_time for s in st])
            m = med[label]
            out.append(Row(nlp, label, len(st), float(np.median(t)),
                           float(np.percentile(t, 95)), float(t.max()),
                           float(np.mean([s.iterations for s in st])),
                           sum(not s.success for s in st), sum(s.fallback for s in st),
                           m / med["hmpc_ipopt"] if "hmpc_ipopt" in med else np.nan,
                           med["authors"] / m if "authors" in med else np.nan,
                           med["do_mpc"] / m if "do_mpc" in med else np.nan))
    return out


def fastest(table: list[Row]) -> str:
    """hmpc's back-end with the lowest median over all solves."""
    cands = [r for r in table if r.nlp == "all" and r.config in HMPC]
    return min(cands, key=lambda r: r.median_ms).config


def profile(splits: list[dict], stats: list, packing: list[float]) -> list[tuple]:
    """Where one back-end's solve time goes: (part, median ms, mean ms, share of mean).

    ``splits``: per solve, CasADi's timers [s] (``t_wall_`` stripped; ``total`` needs
    ``record_time``) and the whole call; solves that fell back to IPOPT are left out.
    The parts (:data:`PARTS`) of the mean add up to the mean call: the QP (CasADi's HPIPM
    interface and HPIPM), function evaluations (all ``nlp_*``), the line search net of
    its ``nlp_fg`` calls, the rest of the solver's ``total`` (IPOPT: its linear algebra
    and algorithm; SQP: its own steps), the buffered call around the solver (copying
    the arrays in and out, ``casadi_call`` - ``total``) and hmpc's Python around that call.
    Below them, not parts: the CasADi call's process (CPU) time (wall above it: the
    process waited for a core), one QP's time (QP time / SQP iterations) and the
    parameter packing, which runs in the closed loop outside the solve timer.
    """
    keep = [s for s, st in zip(splits, stats, strict=True) if not st.fallback]
    if not keep:
        return []
    parts: dict[str, list[float]] = {k: [] for k in PARTS}
    for s in keep:
        call = s["call (hmpc + CasADi)"]
        fev = sum(v for k, v in s.items() if k.startswith("nlp_"))
        ls = max(s.get("linesearch", 0.0) - s.get("nlp_fg", 0.0), 0.0)
        qp = s.get("QP", 0.0)
        total = s.get("total", call)
        casadi = s.get("casadi_call", total)
        for key, v in zip(parts, (qp, fev, ls, total - qp - fev - ls, casadi - total,
                                  call - casadi), strict=True):
            parts[key].append(max(v, 0.0))
    calls = [s["call (hmpc + CasADi)"] for s in keep]
    mean = float(np.mean(calls))
    out = [(k, MS * float(np.median(v)), MS * float(np.mean(v)), float(np.mean(v)) / mean)
           for k, v in parts.items() if max(v) > 0.0]
    out.append(("whole solve call", MS * float(np.median(calls)), MS * mean, 1.0))
    extra = {"CasADi call, CPU (process) time": [s["cpu_casadi_call"] for s in keep
                                                 if "cpu_casadi_call" in s]}
    its = [st.iterations for st in stats if not st.fallback]
    if "QP" in keep[0]:
        extra["one QP (QP time / SQP iterations)"] = [
            s["QP"] / max(n, 1) for s, n in zip(keep, its, strict=True)]
    out += [(k, MS * float(np.median(v)), MS * float(np.mean(v)), np.nan)
            for k, v in extra.items() if v]
    if packing:
        out.append(("parameter packing (closed loop, not timed above)",
                    MS * float(np.median(packing)), MS * float(np.mean(packing)), np.nan))
    return out


#: Step 11's solve-time targets [ms]: (NLP, statistic, bound)
TIME_TARGETS = (("switching", "median_ms", 15.0), ("switching", "p95_ms", 30.0),
                ("all", "median_ms", 3.0), ("all", "p95_ms", 15.0))
#: Step 11's speed-up targets: over IPOPT's defaults (all solves), over do-mpc (final NLP)
X_IPOPT_DEFAULTS, X_DO_MPC = 5.0, 20.0


def targets(table: list[Row], config: str) -> list[str]:
    """Step 11's solve-time targets for one configuration, each with its measured value.

    Switching solves median <= 15 ms and p95 <= 30 ms, all solves median <= 3 ms and p95
    <= 15 ms, >= 5x IPOPT's defaults (medians of all solves), >= 20x do-mpc (medians of
    the final-domain NLP, the one do-mpc solves), no failure.
    """
    get = {(r.nlp, r.config): r for r in table}
    lines = []
    for nlp, stat, bound in TIME_TARGETS:
        row = get.get((nlp, config))
        if row is not None:
            value = getattr(row, stat)
            lines.append(f"{nlp} solves {stat[:-3]} {value:.2f} ms (target <= {bound:g} ms): "
                         f"{_met(value <= bound)}")
    a = get[("all", config)]
    if ("all", "ipopt_defaults") in get:
        x = get[("all", "ipopt_defaults")].median_ms / a.median_ms
        lines.append(f"{x:.1f}x faster than IPOPT defaults, all solves (target >= "
                     f"{X_IPOPT_DEFAULTS:g}x): {_met(x >= X_IPOPT_DEFAULTS)}")
    f = get.get(("final", config))
    if f is not None and np.isfinite(f.dompc_x):
        lines.append(f"{f.dompc_x:.1f}x faster than do-mpc, final NLP (target >= "
                     f"{X_DO_MPC:g}x): {_met(f.dompc_x >= X_DO_MPC)}")
    lines.append(f"failures {a.failures}, fallbacks {a.fallbacks} (target 0 failures): "
                 f"{_met(a.failures == 0)}")
    return lines


def target_sections(table: list[Row], best: str) -> list[tuple[str, list[str]]]:
    """(heading, target lines) for the default configuration and the fastest back-end."""
    configs = {r.config for r in table}
    out = []
    if "hmpc_ipopt" in configs:
        out.append(("hmpc_ipopt, the default configuration", targets(table, "hmpc_ipopt")))
    if best != "hmpc_ipopt":
        out.append((f"{best}, the fastest back-end", targets(table, best)))
    return out


def _met(ok: bool) -> str:
    return "met" if ok else "NOT met"


def _ratio(x: float) -> str:
    return f"{x:.2f}" if np.isfinite(x) else "-"


def text_table(table: list[Row], run) -> str:
    """The table as fixed-width text, one block per NLP."""
    lines = []
    for nlp in NLPS:
        rs = [r for r in table if r.nlp == nlp]
        n = max((r.solves for r in rs), default=0)
        lines += [f"\n{nlp} NLP ({n} solves)",
                  f"  {'configuration':16s} {'median':>8s} {'p95':>8s} {'max':>8s} "
                  f"{'iter':>6s} {'failed':>6s} {'fallbk':>6s} {'/hmpc':>6s} "
                  f"{'authors/x':>9s} {'do-mpc/x':>8s}"]
        lines += [f"  {r.config:16s} {r.median_ms:8.2f} {r.p95_ms:8.2f} {r.max_ms:8.1f} "
                  f"{r.mean_iter:6.1f} {r.failures:6d} {r.fallbacks:6d} "
                  f"{_ratio(r.vs_hmpc):>6s} {_ratio(r.authors_x):>9s} "
                  f"{_ratio(r.dompc_x):>8s}" for r in rs]
    return "\n".join(lines)


def markdown_table(table: list[Row], nlp: str) -> list[str]:
    """One NLP's rows as a Markdown table."""
    out = ["| configuration | solves | median ms | p95 ms | max ms | mean iter | failures | "
           "fallbacks | median / hmpc_ipopt | authors / this | do-mpc / this |",
           "|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|"]
    for r in (r for r in table if r.nlp == nlp):
        out.append(f"| `{r.config}` | {r.solves} | {r.median_ms:.2f} | {r.p95_ms:.2f} | "
                   f"{r.max_ms:.1f} | {r.mean_iter:.1f} | {r.failures} | {r.fallbacks} | "
                   f"{_ratio(r.vs_hmpc)} | {_ratio(r.authors_x)} | {_ratio(r.dompc_x)} |")
    return out


def profile_lines(run, label: str, markdown: bool = False) -> list[str]:
    """The profile of ``label`` on each NLP (text or Markdown)."""
    out = []
    for nlp in ("final", "switching"):
        splits, stats = run.splits.get((label, nlp)), run.stats.get((label, nlp))
        if not splits:
            continue
        prof = profile(splits, stats, run.packing)
        if not prof:  # said, not left out: the fastest back-end may be one of these
            note = (f"{label}, {nlp} NLP: every one of its {len(splits)} solves fell back to "
                    "IPOPT (no profile of its own)")
            out += ["", f"**{note}**"] if markdown else [f"\nwhere the time goes: {note}"]
            continue
        head = f"{label}, {nlp} NLP ({len(splits)} solves; medians and means per solve, ms)"
        if markdown:
            out += ["", f"**{head}**", "", "| part | median ms | mean ms | share of mean |",
                    "|---|--:|--:|--:|"]
            out += [f"| {k} | {md:.3f} | {mn:.3f} | "
                    f"{'-' if not np.isfinite(sh) else f'{100 * sh:.0f} %'} |"
                    for k, md, mn, sh in prof]
        else:
            out += [f"\nwhere the time goes: {head}"]
            out += [f"  {k:54s} {md:8.3f} {mn:8.3f}  "
                    f"{'' if not np.isfinite(sh) else f'{100 * sh:3.0f} %'}"
                    for k, md, mn, sh in prof]
    return out


def machine(argv: list[str], load0: tuple, seconds: float, trials, overrides,
            git: str | None = None) -> dict:
    """The machine and run description: CPU, cores, RAM, OS, versions, date, load.

    Args:
        argv: the command line.
        load0: the load average (1, 5, 15 min) at the start.
        seconds: the suite's wall time [s].
        trials, overrides: the recorded trials and scenario overrides.
        git: ``git describe`` of the code measured (taken at the start).
    """
    def version(pkg: str) -> str | None:
        try:
            return metadata.version(pkg)
        except metadata.PackageNotFoundError:
            return None

    cpu = next((ln.split(":", 1)[1].strip() for ln in _read("/proc/cpuinfo").splitlines()
                if ln.startswith("model name")), platform.processor() or "unknown")
    mem = next((ln.split()[1] for ln in _read("/proc/meminfo").splitlines()
                if ln.startswith("MemTotal")), None)
    osname = next((ln.split("=", 1)[1].strip('"') for ln in
                   _read("/etc/os-release").splitlines() if ln.startswith("PRETTY_NAME")),
                  platform.platform())
    return {"cpu": cpu, "cores": os.cpu_count(),
            "ram_gib": round(int(mem) / 2**20, 1) if mem else None,
            "os": f"{osname} ({platform.platform()})", "python": sys.version.split()[0],
            "casadi": version("casadi"), "numpy": version("numpy"),
            "do_mpc": version("do-mpc"), "hmpc": version("hmpc"), "git": git,
            "date_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "command": shlex.join(argv), "trials": list(trials),
            "overrides": list(overrides),
            "hmpc_build_cache": os.environ.get("HMPC_BUILD_CACHE"),
            "load_average_start": [round(x, 2) for x in load0],
            "load_average_end": [round(x, 2) for x in os.getloadavg()],
            "suite_seconds": round(seconds, 1)}


def _read(path: str) -> str:
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return ""


def git_describe() -> str | None:
    """``git describe --always --dirty`` of this checkout (None outside git)."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        out = subprocess.run(["git", "describe", "--always", "--dirty"], cwd=here,
                             capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def write(run, desc: dict, out: str) -> tuple[str, list[str]]:
    """Writes ``backends.md``, ``backends.csv`` and ``machine.json`` to ``out``.

    Returns:
        (the text report printed to the terminal, the paths written).
    """
    table = rows(run.stats)
    best = fastest(table)
    text = [text_table(table, run), *profile_lines(run, best)]
    if best != "hmpc_ipopt":
        text += profile_lines(run, "hmpc_ipopt")
    for heading, lines in target_sections(table, best):
        text += [f"\nissue targets, {heading}:"] + [f"  {t}" for t in lines]
    text += [f"\nnote: {n}" for n in run.notes]
    text += [f"\nload average {desc['load_average_start']} at start, "
             f"{desc['load_average_end']} at end ({desc['cores']} cores)"]
    os.makedirs(out, exist_ok=True)
    paths = [os.path.join(out, name) for name in ("backends.md", "backends.csv", "machine.json")]
    with open(paths[0], "w") as f:
        f.write("\n".join(markdown(table, run, desc, best)) + "\n")
    with open(paths[1], "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(asdict(table[0])))
        w.writeheader()
        w.writerows({k: round(v, 4) if isinstance(v, float) else v
                     for k, v in asdict(r).items()} for r in table)
    with open(paths[2], "w") as f:
        json.dump({**desc, "build_seconds": {k: round(v, 2) for k, v in run.build.items()},
                   "problems": run.problems, "notes": run.notes}, f, indent=1)
        f.write("\n")
    return "\n".join(text), paths


def markdown(table: list[Row], run, desc: dict, best: str) -> list[str]:
    """The whole report page: machine, legend, tables, profile, targets, notes."""
    out = ["# Benchmark suite: fixed-mode MPC back-ends on recorded closed-loop problems", "",
           f"Generated by `{desc['command']}` on {desc['date_utc']} (hmpc {desc['hmpc']}, "
           f"git {desc['git']}). Problems: the MPC solves of Figure 3 trials "
           f"{', '.join(map(str, desc['trials']))} (10 Hz, plan once, zero-order hold), "
           f"{run.problems.get('final', 0)} final-domain and "
           f"{run.problems.get('switching', 0)} switching, every configuration on each "
           "problem in turn (interleaved). Wall time per solve; ratios are of medians.", "",
           "## Machine", "",
           f"* CPU: {desc['cpu']}, {desc['cores']} cores, {desc['ram_gib']} GiB RAM",
           f"* OS: {desc['os']}",
           f"* Python {desc['python']}, CasADi {desc['casadi']}, NumPy {desc['numpy']}, "
           f"do-mpc {desc['do_mpc'] or 'not installed'}",
           f"* load average (1, 5, 15 min): {desc['load_average_start']} at start, "
           f"{desc['load_average_end']} at end; suite {desc['suite_seconds']} s",
           f"* HMPC_BUILD_CACHE={desc['hmpc_build_cache']} (every NLP in SX)", "",
           "## Configurations", ""]
    out += [f"* `{k}`: {v}" for k, v in LEGEND.items()]
    for nlp in NLPS:
        what = {"final": "Final-domain NLP (no switch left)",
                "switching": "Switching NLP (switches left)",
                "all": "All solves (do-mpc: final only, left out here)"}[nlp]
        out += ["", f"## {what}", "", *markdown_table(table, nlp)]
    out += ["", f"## Where the time goes: {best} (the fastest back-end)",
            *profile_lines(run, best, markdown=True)]
    if best != "hmpc_ipopt":
        out += ["", "For comparison, hmpc's IPOPT:", *profile_lines(run, "hmpc_ipopt", True)]
    for heading, lines in target_sections(table, best):
        out += ["", f"## Issue targets: {heading}", ""] + [f"* {t}" for t in lines]
    if run.notes:
        out += ["", "## Notes", ""] + [f"* {n}" for n in run.notes]
    return out
