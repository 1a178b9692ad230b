"""Where the cells of the grid run: worker processes of this machine (the default), or the workers of a Dask
cluster (`monolib study STUDY --scheduler ADDRESS`, `distributed`).

Either way a cell is one call of `monolib.study.notebooks.run_cell_notebook` (a papermill run of
`ablation_cell.ipynb`), submitted as one task, and `Workers.submit` returns a `concurrent.futures.Future`, so the
runner has one loop for both. On a Dask cluster:

- the workers need the project installed with the same code as the machine that runs `monolib study` (the client),
  and the project's runs folder at the same path (a shared file system): `connect` checks both before any cell is
  submitted, by writing a file into the study's folder that every worker must read back, and by comparing the
  version of the cells' code and the device type;
- the client's `MONOLIB_RUNS`, `MONOLIB_FIGURES` and device (`MONOLIB_DEVICE`) go with every task, so that each
  notebook kernel writes where the client reads and computes the cell's key as the client does;
- a worker that dies mid-cell (killed, out of memory, its node lost) loses only that cell: the scheduler gives it to
  another worker (up to ``distributed.scheduler.allowed-failures`` times, 3 by default; then that cell fails with
  `KilledWorker`, the others go on, and the next run retries it). Nothing the dead worker half-wrote is read: a
  cell's files are written atomically and its `cell.json`, written last, is what marks it complete.
"""
from __future__ import annotations

import concurrent.futures
import hashlib
import os
import uuid
from pathlib import Path
from typing import Callable, Optional

from monolib import locks, paths, versions
from monolib.device import device
from monolib.io import write_text
from monolib.params import Study, StudyError, key_of, load_study
from monolib.study import kernels

CONNECT_SECONDS = 60  # how long to wait for the scheduler and for a first worker (env MONOLIB_CONNECT_SECONDS)


def task_environment() -> dict[str, str]:
    """What a worker's notebook kernel needs from the client's environment: the runs and figures folders (absolute),
    the device type of the cells' keys, whether cells run in warm kernels (`monolib.study.kernels`), and the study locks
    the client holds for them (`monolib.locks`)."""
    return {"MONOLIB_RUNS": str(paths.RUNS.resolve()), "MONOLIB_FIGURES": str(paths.FIGURES.resolve()),
            "MONOLIB_DEVICE": device().type, "MONOLIB_KERNELS": "warm" if kernels.warm_enabled() else "cold",
            locks.ENV: os.environ.get(locks.ENV, "")}  # the study's lock, held by the client for its tasks


FINGERPRINT_ENV = "MONOLIB_FINGERPRINT"  # the client's `fingerprint`, with every task sent to a Dask worker


def fingerprint(study_file: str) -> dict:
    """Everything that decides a cell, computed afresh (no cache: a worker that lives on while the files it runs
    change is seen): the code version of every stage, Python's version and those of every stage's libraries (the
    ones in the stages' keys, `versions.STAGE_LIBRARIES`), and the study as loaded (its `extends` base file
    resolved; its key)."""
    import dataclasses
    import platform

    code = {stage: versions.code_version.__wrapped__(stage) for stage in versions.STAGE_MODULES}
    libraries = {"python": platform.python_version()}
    for stage in versions.STAGE_LIBRARIES:
        libraries.update(versions.library_versions.__wrapped__(stage))
    try:
        spec = dataclasses.asdict(load_study(study_file, check_files=False))
        spec.pop("path", None)
        study = key_of(spec)
    except (StudyError, OSError) as exc:
        study = f"unreadable ({exc})"
    return {"code": code, "libraries": libraries, "study": study}


def differences(mine: dict, theirs: dict) -> list[str]:
    """What differs between two `fingerprint`s, in words (empty when nothing does)."""
    out = [f"code of the {stage} stage" for stage in sorted(set(mine["code"]) | set(theirs["code"]))
           if mine["code"].get(stage) != theirs["code"].get(stage)]
    out += [f"{lib} {theirs['libraries'].get(lib)} (client {mine['libraries'].get(lib)})"
            for lib in sorted(set(mine["libraries"]) | set(theirs["libraries"]))
            if mine["libraries"].get(lib) != theirs["libraries"].get(lib)]
    if mine["study"] != theirs["study"]:
        out.append(f"the study as loaded ({theirs['study']}, client {mine['study']})")
    return out


def check_fingerprint(study_file: str, expected_json: str) -> None:
    """Run by every cell task on a Dask worker before it computes: `StudyError` when the worker's `fingerprint`
    (computed now, not at connection) differs from the client's."""
    import json
    import socket

    diff = differences(json.loads(expected_json), fingerprint(study_file))
    if diff:
        raise StudyError(f"worker {socket.gethostname()} (pid {os.getpid()}) no longer computes cells as the client: "
                         + "; ".join(diff) + " (install the client's version of the project and its libraries)")


def worker_facts(token: str, study_file: str, device_type: str) -> dict:
    """Run on each worker by `connect`: can it read the client's files, and does it compute cells as the client."""
    import torch

    study = Path(study_file)
    return {"pid": os.getpid(), "token": Path(token).is_file(),
            "study_sha": hashlib.sha256(study.read_bytes()).hexdigest() if study.is_file() else None,
            "fingerprint": fingerprint(study_file) if study.is_file() else None,
            "device_ok": device_type == "cpu" or torch.cuda.is_available()}


class Workers:
    """The cells' workers: `jobs` local processes (`scheduler` None), or the workers of the Dask scheduler at
    `scheduler` (``tcp://host:8786``, or a scheduler file written by ``dask scheduler --scheduler-file``). A context
    manager; `submit(name, fn, *args)` returns a `concurrent.futures.Future`."""

    def __init__(self, study: Study, jobs: int, scheduler: Optional[str] = None):
        self.study, self.jobs, self.scheduler = study, jobs, scheduler
        self.client = None
        self.pool = None

    def __enter__(self) -> "Workers":
        if self.scheduler is None:
            self.pool = concurrent.futures.ProcessPoolExecutor(max_workers=self.jobs)
        else:
            self.client = connect(self.scheduler, self.study)
            self.pool = self.client.get_executor(pure=False)
        return self

    def __exit__(self, *exc) -> None:
        if self.client is not None:
            self.client.close()
        else:
            self.pool.shutdown(wait=True, cancel_futures=exc[0] is not None)

    def describe(self) -> str:
        if self.client is None:
            return f"{self.jobs} local worker processes"
        return f"{len(self.client.scheduler_info()['workers'])} Dask workers of {self.client.scheduler.address}"

    def submit(self, name: str, fn: Callable, *args) -> concurrent.futures.Future:
        if self.client is None:
            return self.pool.submit(fn, *args)
        return self.pool.submit(fn, *args, key=f"cell {name} {uuid.uuid4().hex[:8]}")  # named in the dashboard


def scheduler_address(scheduler: str) -> str:
    """The address of a ``--scheduler`` value that is not a file: ``tcp://host:port`` (or ``host:port``, another
    protocol of Dask's, ``inproc://...``); `StudyError` for anything else (a scheduler file's path that does not
    exist, a host without a port)."""
    import re

    if re.fullmatch(r"(tcp|tls|ucx|ws|wss)://[^\s/]+:\d+|inproc://\S+|[\w.\-]+:\d+", scheduler):
        return scheduler
    if "://" in scheduler:
        raise StudyError(f"--scheduler {scheduler}: expected an address with a port (tcp://host:8786)")
    raise StudyError(f"--scheduler {scheduler}: neither a scheduler file (no such file) nor an address "
                     f"(tcp://host:8786, or the file `dask scheduler --scheduler-file FILE` wrote)")


def check(scheduler: str, study: Study) -> None:
    """`connect` and close: the study runner calls it before its first stage, so that a wrong address or a worker
    that cannot run the cells stops the run before hours of perception."""
    connect(scheduler, study).close()


def connect(scheduler: str, study: Study, timeout: Optional[float] = None):
    """A `distributed.Client` of the scheduler, once at least one worker is connected (within `timeout` seconds)
    and every worker has passed `worker_facts`; otherwise one `StudyError` saying what is wrong with which worker."""
    from distributed import Client

    timeout = timeout or float(os.environ.get("MONOLIB_CONNECT_SECONDS", CONNECT_SECONDS))
    kwargs = {"scheduler_file": scheduler} if Path(scheduler).is_file() else {"address": scheduler_address(scheduler)}
    try:
        client = Client(timeout=timeout, **kwargs)
    except ValueError as exc:  # a scheduler file that is not one
        raise StudyError(f"--scheduler {scheduler}: not a Dask scheduler file ({exc})") from None
    except (OSError, TimeoutError) as exc:
        raise StudyError(f"--scheduler {scheduler}: no Dask scheduler answered within {timeout:g} s ({exc}); "
                         f"start one with `dask scheduler` and workers with `dask worker ADDRESS`") from None
    try:
        client.wait_for_workers(1, timeout=timeout)
    except (TimeoutError, OSError):
        client.close()
        raise StudyError(f"--scheduler {scheduler}: no worker connected within {timeout:g} s; start them with "
                         f"`dask worker {client.scheduler.address} --nthreads 1`") from None
    env = task_environment()
    token = Path(env["MONOLIB_RUNS"]) / study.name / f".workers-{uuid.uuid4().hex}"
    write_text(token, "a worker that reads this file shares the runs folder of the client\n")
    try:
        facts = client.run(worker_facts, str(token), str(study.path), env["MONOLIB_DEVICE"])
    finally:
        token.unlink(missing_ok=True)
    sha = hashlib.sha256(Path(study.path).read_bytes()).hexdigest()
    mine = fingerprint(str(study.path))
    problems = []
    for address, f in sorted(facts.items()):
        if not f["token"]:
            problems.append(f"{address}: cannot see {token.parent} (the workers need the runs folder of this machine "
                            f"at the same path: a shared file system)")
        if f["study_sha"] != sha:
            problems.append(f"{address}: {'has another' if f['study_sha'] else 'cannot read the'} study file "
                            f"{study.path}")
        diff = differences(mine, f["fingerprint"]) if f["fingerprint"] is not None else []
        if diff:
            problems.append(f"{address}: computes cells otherwise: {'; '.join(diff)} (install this project's version "
                            f"and its libraries on the workers)")
        if not f["device_ok"]:
            problems.append(f"{address}: has no CUDA device, and the cells' keys were computed for one "
                            f"(MONOLIB_DEVICE={env['MONOLIB_DEVICE']} here)")
    if problems:
        client.close()
        raise StudyError(f"--scheduler {scheduler}: {len(problems)} problem(s) with the workers:\n  "
                         + "\n  ".join(problems))
    return client
