"""``hmpc sweep --dask`` without a shared file system: results travel through the futures.

The workers of the test cluster run in their own directories and are forbidden (by an
audit hook) to open, create, rename or remove anything under the client's directory, as
on a cluster whose machines do not share the client's disk.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import cli_env
from test_sweep import REGISTER, TIMING, TINY_SET, table, write_sweep
from hmpc_cli.sweep import dask as sweep_dask
from hmpc_cli.log.reader import read_log
from hmpc_cli.analysis.replay import compare_logs
from hmpc_cli.sweep.execute import execute_sweep
from hmpc_cli.sweep.plan import plan_sweep
from hmpc_cli.sweep.dask import TransferError, collect, store_run

distributed = pytest.importorskip("distributed")

SMALL = """name = "small"
scenario = "{scenario}"
seeds = [3]
""" + TINY_SET + """
[grid]
case = [
  { label = "ok", "lowlevel.kp" = 1.0 },
  { label = "crash", "replanning.policy" = "on_contact", "replanning.contact_guards" = ["nope"] },
]
"""
#: audit events whose path arguments a sandboxed worker may not point at the client's disk
_EVENTS = {"open", "os.mkdir", "os.rename", "os.replace", "os.remove", "os.rmdir",
           "os.listdir", "os.scandir", "shutil.rmtree", "os.chdir", "os.truncate"}


class Sandbox(distributed.WorkerPlugin):
    """Moves a worker into its own directory and forbids it the client's directory."""

    name = "hmpc-sandbox"

    def __init__(self, forbidden: str) -> None:
        self.forbidden = forbidden
        self.logs: list[str] = []  # run logs the worker opened

    def setup(self, worker) -> None:
        os.chdir(worker.local_directory)
        forbidden, logs = self.forbidden, self.logs

        def hook(event: str, args: tuple) -> None:
            if event not in _EVENTS:
                return
            for arg in args:
                if isinstance(arg, (str, bytes, os.PathLike)):
                    path = os.path.abspath(os.fsdecode(arg))
                    if path == forbidden or path.startswith(forbidden + os.sep):
                        raise PermissionError(f"sandboxed worker: {path} is the client's")
                    if event == "open" and path.endswith("run.mcap"):
                        logs.append(path)

        sys.addaudithook(hook)


def _worker_state(dask_worker) -> dict:
    """The sandbox's record and what is left in the worker's own directory."""
    here = Path(dask_worker.local_directory)
    return {"dir": str(here), "cwd": os.getcwd(),
            "logs": list(dask_worker.plugins[Sandbox.name].logs),
            "left": sorted(p.name for p in here.rglob("hmpc-run-*"))}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """(client folder, sweep file, local sweep output, Dask client): one sandboxed worker."""
    base = tmp_path_factory.mktemp("remote")
    client_dir = base / "client"
    client_dir.mkdir()
    path = write_sweep(client_dir, SMALL)
    local = client_dir / "local"
    outcome = execute_sweep(plan_sweep(path), local)
    assert outcome.done == 2 and not outcome.lost
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                  dashboard_address=None,
                                  local_directory=str(base / "workers")) as cluster, \
            distributed.Client(cluster) as client:
        client.register_plugin(Sandbox(str(client_dir.resolve())))
        yield client_dir, path, local, client


def _files(out: Path) -> dict[str, bytes]:
    return {p.relative_to(out).as_posix(): p.read_bytes()
            for p in sorted((out / "runs").rglob("*")) if p.is_file()}


def test_dask_results_travel_through_the_futures(setup):
    client_dir, path, local, client = setup
    (state,) = client.run(_worker_state).values()
    assert not Path(state["cwd"]).is_relative_to(client_dir)
    with pytest.raises(PermissionError, match="is the client's"):  # the sandbox holds
        client.submit(Path.write_text, client_dir / "x", "y", pure=False).result()
    out = client_dir / "dask"
    outcome = execute_sweep(plan_sweep(path), out, client=client)
    assert outcome.lost == [] and outcome.done == 2 and outcome.ran == 2
    assert table(out) == table(local)
    mine, theirs = _files(out), _files(local)
    assert sorted(mine) == sorted(theirs)  # run.mcap, summary.json, scenario.toml, error.txt
    assert {Path(n).name for n in mine} == {"run.mcap", "summary.json", "scenario.toml",
                                             "error.txt"}
    for name in mine:
        if name.endswith("summary.json"):
            a, b = json.loads(mine[name]), json.loads(theirs[name])
            assert {k: v for k, v in a.items() if k not in TIMING} == \
                {k: v for k, v in b.items() if k not in TIMING}
        elif name.endswith("run.mcap"):
            assert compare_logs(read_log(local / name).messages,
                                read_log(out / name).messages) is None
        elif name.endswith("scenario.toml"):
            assert mine[name] == theirs[name]
    (state,) = client.run(_worker_state).values()
    assert state["logs"] and all(Path(p).is_relative_to(state["dir"]) for p in state["logs"])
    assert state["left"] == []  # each run's temporary directory was removed
    assert not [p for p in (out / "runs").iterdir() if p.name.startswith(".")]


def test_dask_run_logs_record_the_sweep_provenance(setup):
    client_dir, path, _, client = setup
    out = client_dir / "dask"
    if not (out / "results.csv").is_file():
        execute_sweep(plan_sweep(path), out, client=client)
    (ok,) = [r for r in table(out) if r["case"] == "ok"]
    info = read_log(out / ok["log"]).topic("/run/info")[0].data
    assert "lowlevel.kp=1.0" in info["overrides"] and info["overrides"][-1] == "seed=3"
    assert "sim.duration=0.3" in info["overrides"] and info["sweep"] == str(path)
    assert info["command"] == shlex.join(sys.argv)  # the client's, not the worker's


def test_a_failed_transfer_writes_nothing_and_is_redone(setup, monkeypatch):
    client_dir, path, local, client = setup
    out = client_dir / "lossy"
    real, calls = store_run, []

    def flaky(out_dir, run_id, payload):
        calls.append(run_id)
        if len(calls) == 1:  # the first result breaks off while being written
            payload = {**payload, "files": {**payload["files"], "zz": "not bytes"}}
        return real(out_dir, run_id, payload)

    monkeypatch.setattr(sweep_dask, "store_run", flaky)
    first = execute_sweep(plan_sweep(path), out, client=client)
    assert len(first.lost) == 1
    assert first.lost[0].startswith(f"{calls[0]}: results not stored: TransferError")
    assert first.done == 1 and not (out / "runs" / calls[0]).exists()
    assert sorted(p.name for p in (out / "runs").iterdir()) == sorted(calls[1:])
    again = execute_sweep(plan_sweep(path), out, client=client)
    assert (again.skipped, again.ran, again.lost, again.done) == (1, 1, [], 2)
    assert calls[2:] == calls[:1]
    assert table(out) == table(local)


#: ``hmpc sweep`` whose client's disk is full: storing any run's files fails (ENOSPC)
FULL_DISK = ("import errno\n"
             "from hmpc_cli.sweep import dask\n"
             "def store_run(out, run_id, payload):\n"
             "    raise OSError(errno.ENOSPC, 'No space left on device', str(out / 'runs'))\n"
             "dask.store_run = store_run\n")


def test_a_full_disk_stops_a_dask_sweep_with_one_line(setup):
    client_dir, path, _, client = setup
    out = client_dir / "full"
    proc = subprocess.run([sys.executable, "-c", FULL_DISK + REGISTER, "sweep", str(path),
                           "--dask", client.scheduler.address, "--out", str(out)],
                          cwd=client_dir, env=cli_env(), capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"error: cannot write: {out / 'runs'}: No space left on device; 0 of 2 runs kept in "
        f"{out} (finished runs stay; free space and run the same command to resume)"]
    assert list((out / "runs").iterdir()) == []


# ------------------------------------------------------------ storing, no cluster
def _payload(files: dict) -> dict:
    summary = {"success": True, "reason": ""}
    return {"summary": summary, "files": {"summary.json": json.dumps(summary).encode(),
                                          **files}}


def test_store_run_replaces_a_partial_run_atomically(tmp_path):
    runs = tmp_path / "runs"
    (runs / "abc").mkdir(parents=True)
    (runs / "abc" / "run.mcap").write_bytes(b"partial")
    summary = store_run(tmp_path, "abc", _payload({"run.mcap": b"log", "sub/x.txt": b"x"}))
    assert summary == {"success": True, "reason": ""}
    assert (runs / "abc" / "run.mcap").read_bytes() == b"log"
    assert (runs / "abc" / "sub" / "x.txt").read_bytes() == b"x"
    assert sorted(p.name for p in runs.iterdir()) == ["abc"]


@pytest.mark.parametrize("files, why", [
    ({"../evil": b"x"}, "leaves the run directory"),
    ({"/abs": b"x"}, "leaves the run directory"),
    ({"a//b": b"x"}, "leaves the run directory"),
    ({"run.mcap": "text"}, "not bytes"),
])
def test_store_run_refuses_a_bad_payload_and_writes_nothing(tmp_path, files, why):
    (tmp_path / "runs" / "abc").mkdir(parents=True)
    (tmp_path / "runs" / "abc" / "run.mcap").write_bytes(b"partial")
    with pytest.raises(TransferError, match=why):
        store_run(tmp_path, "abc", _payload(files))
    assert [p.name for p in (tmp_path / "runs").iterdir()] == ["abc"]
    assert (tmp_path / "runs" / "abc" / "run.mcap").read_bytes() == b"partial"
    assert not (tmp_path / "evil").exists()


def test_store_run_failing_midway_leaves_nothing(tmp_path, monkeypatch):
    (tmp_path / "runs").mkdir()
    real, n = os.fsync, []

    def full_disk(fd):
        n.append(fd)
        if len(n) == 2:
            raise OSError(28, "No space left on device")
        real(fd)

    monkeypatch.setattr(sweep_dask.os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space"):
        store_run(tmp_path, "abc", _payload({"run.mcap": b"log"}))
    assert list((tmp_path / "runs").iterdir()) == []


def test_summary_must_match_its_file(tmp_path):
    (tmp_path / "runs").mkdir()
    bad = _payload({})
    bad["summary"] = {"success": False}
    with pytest.raises(TransferError, match="differs"):
        store_run(tmp_path, "abc", bad)
    with pytest.raises(TransferError, match="no summary.json"):
        store_run(tmp_path, "abc", {"summary": {}, "files": {}})
    assert list((tmp_path / "runs").iterdir()) == []


def test_a_failed_future_is_lost_not_recorded(tmp_path):
    class Dead:
        def result(self):
            raise OSError("connection to the worker lost")

    class Run:
        run_id = "abc"

    (tmp_path / "runs").mkdir()
    lost, recorded = [], []
    collect(Dead(), Run(), tmp_path, lambda r, s: recorded.append(r), lost)
    assert lost == ["abc: worker failed: OSError: connection to the worker lost"] and recorded == []
    assert list((tmp_path / "runs").iterdir()) == []


def test_stale_staging_directories_are_cleared(tmp_path):
    runs = tmp_path / "runs"
    for name in (".abc.part-x1", ".abc.old-1234", "abc", ".keep"):
        (runs / name).mkdir(parents=True)
    sweep_dask.clear_stale(runs)
    assert sorted(p.name for p in runs.iterdir()) == [".keep", "abc"]


def test_a_margins_file_the_worker_lacks_makes_its_run_lost_not_failed(tmp_path):
    """The workers need no shared file system but for a margins file: the task carries
    its path and sha256, and a worker without it (or with another file there) fails the
    task before running, so the run is lost (exit 1, redone), not tabled as a controller
    whose margins were refused."""
    from hmpc_cli.core.paths import file_digest

    margins = Path(__file__).resolve().parents[1] / "scenarios" / "margins" / "ball_fig3.toml"
    toml = f'[mpc]\nmargins = "{margins}"\n'
    assert sweep_dask.needed_files(toml) == {str(margins): file_digest(margins)}
    assert sweep_dask.needed_files('[mpc]\nmargins = "tube"\n') == {}
    assert sweep_dask.needed_files("[mpc]\n") == {}
    sweep_dask.check_needed(sweep_dask.needed_files(toml))  # here: the same file
    for needed in ({str(tmp_path / "gone.toml"): file_digest(margins)},
                   {str(margins): "sha256:" + "0" * 64}):
        with pytest.raises(FileNotFoundError) as exc:
            sweep_dask.run_remote(toml, None, needed)
        assert str(exc.value).endswith("a margins file must be readable at the same path "
                                       "with the same content on every worker")
