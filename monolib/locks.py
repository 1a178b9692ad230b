"""One run at a time writes into a study's folders: `study_lock` around `monolib study` and `prepare`.

Two runs of one study at once (two terminals, a notebook beside the command line, the Dask grid started twice)
would otherwise write the same cell folders and the same dataset. The lock is an advisory `flock` on
``runs/<study>/.lock`` (and on the data folder a study shares with its base, ``runs/<base>/.lock``): the kernel drops
it when its process ends, however it ends, so a killed run leaves no stale lock. A second run prints one line
naming the first (its host, pid, command and start time, written into the lock file) and waits for it.

The processes a run starts for its own work (the grid's worker processes, their notebook kernels, Dask tasks) get
``MONOLIB_LOCKED`` in their environment and do not lock again. `flock` holds between the processes of one machine;
on a network file system it depends on the server (NFSv4 supports it), so a cluster's runs are best started from
one machine, as `monolib study --scheduler` does.
"""
from __future__ import annotations

import fcntl
import os
import socket
import sys
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Iterator

ENV = "MONOLIB_LOCKED"  # folders (os.pathsep-separated) whose lock a parent process of this one holds
_held: dict[str, int] = {}  # folder -> depth, in this process (a lock is re-entrant within its process)


def _inherited() -> set[str]:
    return {p for p in os.environ.get(ENV, "").split(os.pathsep) if p}


@contextmanager
def _one(folder: Path, wait: bool) -> Iterator[None]:
    key = str(folder.resolve())
    if key in _held or key in _inherited():
        _held[key] = _held.get(key, 0) + 1
        try:
            yield
        finally:
            _held[key] -= 1
            if not _held[key]:
                del _held[key]
        return
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / ".lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = Path(path).read_text(errors="replace").strip() or "another process"
            if not wait:
                raise RunInProgress(f"{folder}: in use by {holder}") from None
            print(f"{folder}: in use by {holder}; waiting for it to finish (Ctrl-C to stop)", file=sys.stderr,
                  flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        os.ftruncate(fd, 0)
        os.pwrite(fd, (f"pid {os.getpid()} on {socket.gethostname()} since "
                       f"{time.strftime('%Y-%m-%d %H:%M:%S')} ({' '.join(sys.argv[:3])})\n").encode(), 0)
        _held[key] = 1
        os.environ[ENV] = os.pathsep.join(sorted(_inherited() | {key}))  # for the processes this run starts
        try:
            yield
        finally:
            del _held[key]
            os.environ[ENV] = os.pathsep.join(sorted(_inherited() - {key}))
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # drops the lock


class RunInProgress(RuntimeError):
    """Another run holds the study's lock (with ``wait=False``)."""


@contextmanager
def study_lock(*folders: Path, wait: bool = True) -> Iterator[None]:
    """Hold the lock of each folder (sorted, each once, so that two runs never wait for each other crosswise)."""
    with ExitStack() as stack:
        for folder in sorted({Path(f).resolve() for f in folders}):
            stack.enter_context(_one(folder, wait))
        yield


def of_study(study, wait: bool = True):
    """The lock a study's writers hold: its own folder and the data folder it may share with its base study. Taken
    by `monolib study` and `prepare`, and by a notebook around a stage it runs itself."""
    return study_lock(study.dir, study.data_dir, wait=wait)
