"""``hmpc sweep --dask``: runs on a Dask cluster, results back through the futures.

A worker needs no view of the client's disk but a scenario's margins file (``mpc.margins``
as a file), which must be at the same path with the same content (checked by its sha256:
else the run is lost, not failed): it runs in a temporary directory of its own
(under the Dask worker's local directory), returns the run's summary and every file of
the run directory (``scenario.toml``, ``run.mcap``, ``summary.json``, ``error.txt``...) as
bytes through the future, and removes its directory. The client writes the files into
``<out>/runs/<run_id>/`` atomically: into a hidden staging directory first, renamed into
place only when every file is written. A run whose transfer or store fails leaves nothing
behind (an earlier partial run directory stays as it was): it is reported as lost and
redone when the sweep is resumed. A disk error storing a run (a full or read-only disk,
:func:`hmpc_cli.core.paths.disk_error`) stops the sweep: the remaining futures are
cancelled and the error raised, as the local paths do.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Callable
from pathlib import Path, PurePosixPath

__all__ = ["TransferError", "check_needed", "needed_files", "run_on_dask", "run_remote",
           "store_run"]

_PART, _OLD = ".part-", ".old-"  # staging and replaced run directories (hidden, in runs/)


class TransferError(ValueError):
    """A run's result that cannot be stored (malformed payload); the message says why."""


# ------------------------------------------------------------------ the worker side
def _scratch() -> str | None:
    """The Dask worker's local directory, or None (the system's temporary directory)."""
    try:
        from distributed import get_worker

        return get_worker().local_directory
    except (ImportError, ValueError, AttributeError):
        return None


def needed_files(toml_text: str) -> dict[str, str]:
    """The files a run reads from the client's disk: its margins file, path -> sha256.

    (``mpc.margins`` as a file, made absolute when the sweep planned the run; a file
    missing on the client is the sweep's own check's to report.)
    """
    from hmpc_cli.core.paths import file_digest
    from hmpc_cli.sweep.table import margins_file_of

    source = margins_file_of(toml_text)
    if source is None or not Path(source).is_file():
        return {}
    return {source: file_digest(Path(source))}


def check_needed(needed: dict[str, str]) -> None:
    """Raises when a file the run reads is not on this worker as on the client.

    Raises:
        FileNotFoundError: missing, unreadable, or other content (its sha256): the run
            would fail for the worker's disk, not for the controller.
    """
    from hmpc_cli.core.paths import file_digest

    for source, digest in needed.items():
        try:
            same = file_digest(Path(source)) == digest
        except OSError:
            same = False
        if not same:
            raise FileNotFoundError(
                f"mpc.margins: {source} is not on this Dask worker as on the client "
                f"(missing, unreadable or another file): a margins file must be readable "
                f"at the same path with the same content on every worker")


def run_remote(toml_text: str, provenance=None, needed: dict[str, str] | None = None
               ) -> dict:
    """Runs one effective scenario in a private temporary directory; returns its results.

    Args:
        toml_text: the run's effective scenario.
        provenance: the run's :class:`hmpc_cli.log.runlog.Provenance` (recorded in its log).
        needed: the client's files it reads (:func:`needed_files`), checked first
            (:func:`check_needed`): one not here fails the task, so the run is lost and
            redone, not tabled as a controller that failed.

    Returns:
        ``{"summary": dict, "files": {relative posix path: bytes}}``: the run directory's
        files; the directory itself is removed.
    """
    from hmpc_cli.run.runner import run_one

    check_needed(needed or {})

    with tempfile.TemporaryDirectory(prefix="hmpc-run-", dir=_scratch()) as tmp:
        run_dir = Path(tmp) / "run"
        summary = run_one(toml_text, str(run_dir), provenance)
        files = {p.relative_to(run_dir).as_posix(): p.read_bytes()
                 for p in sorted(run_dir.rglob("*")) if p.is_file()}
    return {"summary": summary, "files": files}


# ------------------------------------------------------------------ the client side
def _checked_files(payload) -> tuple[dict, dict[str, bytes]]:
    """The payload's summary and files, checked before anything is written.

    Raises:
        TransferError: not a run's result, a file name that would leave the run
            directory, content that is not bytes, or a summary.json that is not the
            returned summary.
    """
    if not isinstance(payload, dict) or not isinstance(payload.get("files"), dict):
        raise TransferError(f"not a run result: {type(payload).__name__}")
    files = payload["files"]
    for name, data in files.items():
        path = PurePosixPath(name) if isinstance(name, str) else None
        if (path is None or path.is_absolute() or "\\" in name
                or any(part in ("", ".", "..") for part in name.split("/"))):
            raise TransferError(f"file name {name!r} leaves the run directory")
        if not isinstance(data, bytes):
            raise TransferError(f"{name}: content is {type(data).__name__}, not bytes")
    try:
        summary = json.loads(files["summary.json"])
    except KeyError:
        raise TransferError("no summary.json among the run's files") from None
    except ValueError as exc:
        raise TransferError(f"summary.json is not JSON: {exc}") from None
    if not isinstance(summary, dict) or summary != payload.get("summary"):
        raise TransferError("summary.json differs from the returned summary")
    return summary, files


def store_run(out: Path, run_id: str, payload) -> dict:
    """Writes a run's returned files to ``<out>/runs/<run_id>/`` atomically.

    The files go to a hidden staging directory in ``<out>/runs/`` which is renamed into
    place when complete (a previous directory of the run is replaced then); on any
    failure the staging directory is removed and the run directory left as it was.

    Returns:
        The run's summary.

    Raises:
        TransferError: a malformed payload (nothing written).
        OSError: the files could not be written (nothing left behind).
    """
    summary, files = _checked_files(payload)
    runs = out / "runs"
    stage = Path(tempfile.mkdtemp(prefix=f".{run_id}{_PART}", dir=runs))
    try:
        for name, data in files.items():
            path = stage / name
            path.parent.mkdir(parents=True, exist_ok=True)
            with open(path, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
        _swap_in(stage, runs / run_id)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return summary


def _swap_in(stage: Path, target: Path) -> None:
    """Renames ``stage`` to ``target``, replacing (then removing) an existing ``target``."""
    old = None
    if target.exists() or target.is_symlink():
        old = target.with_name(f".{target.name}{_OLD}{uuid.uuid4().hex[:8]}")
        os.rename(target, old)
    try:
        os.rename(stage, target)
    except BaseException:
        if old is not None:
            os.rename(old, target)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def clear_stale(runs: Path) -> None:
    """Removes staging and replaced directories a killed client left in ``runs``."""
    for path in runs.glob(".*"):
        if (_PART in path.name or _OLD in path.name) and path.is_dir():
            shutil.rmtree(path, ignore_errors=True)


def collect(fut, run, out: Path, record: Callable, lost: list[str]) -> None:
    """Stores and records one finished future; a failed transfer or store goes to ``lost``.

    Raises:
        OSError: a disk error storing the run (:func:`hmpc_cli.core.paths.disk_error`).
    """
    from hmpc_cli.core.paths import disk_error

    try:
        payload = fut.result()
    except Exception as exc:  # broad on purpose: the worker (not the run) failed
        lost.append(f"{run.run_id}: worker failed: {type(exc).__name__}: {exc}")
        return
    try:
        summary = store_run(out, run.run_id, payload)
    except (TransferError, OSError) as exc:
        if disk_error(exc):  # this machine's disk: every later run would fail the same way
            raise
        lost.append(f"{run.run_id}: results not stored: {type(exc).__name__}: {exc}")
        return
    record(run, summary)


def run_on_dask(client, pending: list, out: Path, record: Callable, lost: list[str],
                provenance: Callable) -> None:
    """Runs ``pending`` on the Dask ``client``'s cluster; stores each run as it finishes.

    Args:
        client: a connected ``distributed.Client``.
        pending: the runs (:class:`hmpc_cli.sweep.plan.Run`).
        out: the sweep's output directory (on this machine only).
        record: ``record(run, summary)`` for every stored run.
        lost: receives one line per run whose worker, transfer or store failed.
        provenance: ``provenance(run)``, the run's :class:`hmpc_cli.log.runlog.Provenance`.

    Raises:
        KeyboardInterrupt: a stop signal (the remaining futures are cancelled first).
        OSError: a disk error storing a run (the remaining futures are cancelled first).
    """
    from distributed import as_completed

    clear_stale(out / "runs")
    futures = {client.submit(run_remote, r.toml, provenance(r), needed_files(r.toml),
                             pure=False): r
               for r in pending}
    try:
        for fut in as_completed(list(futures)):
            run = futures.pop(fut)
            collect(fut, run, out, record, lost)
            fut.release()  # the worker may drop the result (about 1 MB per run)
    except BaseException:  # a stop signal or a disk error: nothing more is stored
        client.cancel(list(futures))
        raise
