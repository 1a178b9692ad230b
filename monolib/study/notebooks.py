"""Running a notebook with papermill: the grid's cell notebook (`run_cell_notebook`, one call per cell on a worker)
and the report notebook, each in its own kernel or a worker's warm kernel (`monolib.study.kernels`), with the kernel
settings of every run (`kernel_config`), a check that the grid's parameters are declared before any work
(`check_notebook_parameters`), and a failing notebook cell as one readable error (`NotebookFailed`).
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from monolib import paths
from monolib.params import StudyError
from monolib.retrieval.grid import CellSpec
from monolib.study import cluster, kernels

log = logging.getLogger(__name__)
CELL_NOTEBOOK = paths.NOTEBOOKS / "ablation_cell.ipynb"
REPORT_NOTEBOOK = paths.NOTEBOOKS / "report.ipynb"


def check_notebook_parameters(notebook: Path, names: set[str]) -> None:
    """Fail before any work when the grid sets a parameter the notebook does not declare."""
    import papermill

    declared = set(papermill.inspect_notebook(str(notebook)))
    missing = sorted(names - declared)
    if missing:
        raise StudyError(f"{notebook}: no parameter named {', '.join(missing)} "
                         f"(declared: {', '.join(sorted(declared))})")


class NotebookFailed(RuntimeError):
    """A notebook run stopped: which notebook cell raised what, and where the executed notebook (with the full
    traceback) is. One plain message, so that it pickles back from a worker process and reads in a log."""


def kernel_config():
    """The kernel settings of every notebook the runner executes (papermill's `config`, read by nbclient and
    jupyter_client), so that a log of the run holds the run and not the kernels' plumbing:

    - the kernel's channels are Unix sockets of its own in Jupyter's runtime folder (`transport = "ipc"`, a new
      `ip` prefix per call), not TCP ports: ipykernel 7 no longer warns, for every notebook, "Kernel is running
      over TCP without encryption", and parallel kernels cannot collide on a port ("ZMQError: Address already in
      use"). Where Unix sockets cannot be used (Windows, or a runtime folder whose path is too long for a socket
      name): TCP with CurveZMQ keys provisioned by the manager (`transport_encryption = "auto"`), which also ends
      the warning;
    - the kernel process logs only critical errors (`IPKernelApp.log_level`): jupyter_client interrupts a kernel
      before shutting it down, and now and then ipykernel reports that interrupt as "ERROR | KeyboardInterrupt
      caught in kernel". A notebook's own errors are not kernel log lines: they reach the executed notebook and
      `NotebookFailed`."""
    import uuid

    import zmq
    from jupyter_core.paths import jupyter_runtime_dir
    from traitlets.config import Config

    prefix = os.path.join(jupyter_runtime_dir(), f"kernel-{uuid.uuid4()}-ipc")  # sockets: prefix-1 ... prefix-5
    config = Config({"NotebookClient": {"extra_arguments": ["--IPKernelApp.log_level=CRITICAL"]}})
    if os.name == "posix" and len(prefix.encode()) < 96:  # a socket's path: at most 107 bytes on Linux, 103 on macOS
        os.makedirs(os.path.dirname(prefix), mode=0o700, exist_ok=True)
        config.KernelManager.transport = "ipc"
        config.KernelManager.ip = prefix
    elif zmq.has("curve"):
        config.KernelManager.transport_encryption = "auto"
    return config


def _ansi_free(text: str) -> str:
    import re

    return re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", text)


def failure_message(notebook: Path, output: Path, exc) -> str:
    """A `PapermillExecutionError` in a few readable lines: the notebook cell (its number and first line of code),
    the error, the last lines of its traceback, and the executed notebook that holds the rest."""
    lines = [ln for ln in _ansi_free(exc.source).splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    tb = [ln for ln in _ansi_free("\n".join(exc.traceback or [])).splitlines()
          if ln.strip() and ln.strip("- ") and "Traceback (most recent call last)" not in ln]
    where = f"In [{exc.exec_count}]" + (f" ({lines[0].strip()[:80]})" if lines else "")  # as the notebook shows it
    tail = "".join(f"\n    {ln}" for ln in tb[-7:-1])  # the lines nearest the error (the error: first line)
    return (f"{notebook.name}: {where} raised {exc.ename}: {exc.evalue}{tail}\n"
            f"  executed notebook: {output}")


def execute(notebook: Path, output: Path, parameters: dict, timeout: int, retries: int = 1,
            warm: bool = False, env: dict[str, str] | None = None) -> Path:
    """Run a notebook with papermill (explicit kernel, cwd and timeout, `kernel_config`): in its own kernel, or with
    `warm` in this worker's warm kernel (`monolib.study.kernels`, which inherits `env`). A failing notebook cell raises
    `NotebookFailed` naming the cell and the executed notebook (papermill writes it, traceback included). Any other
    failure (a kernel that did not start, died or timed out) is retried `retries` times, in a fresh kernel; a warm
    kernel is discarded after any failure, so no notebook inherits a broken one."""
    import papermill

    output.parent.mkdir(parents=True, exist_ok=True)
    for attempt in range(retries + 1):
        try:
            if warm:
                kernels.execute(str(notebook), str(output), parameters, timeout, str(notebook.parent), env or {},
                                kernel_config())
            else:
                papermill.execute_notebook(str(notebook), str(output), parameters=parameters, kernel_name="python3",
                                           cwd=str(notebook.parent), execution_timeout=timeout, progress_bar=False,
                                           log_output=False, config=kernel_config())
            return output
        except papermill.PapermillExecutionError as exc:
            if warm:
                kernels.discard()
            raise NotebookFailed(failure_message(notebook, output, exc)) from None
        except Exception as exc:  # the kernel failed: start-up (ZMQError, timeouts), death, a cell's timeout
            if warm:
                kernels.discard()
            if attempt == retries:
                raise
            log.warning("%s: the kernel failed (%s: %s); running it again in a fresh kernel", notebook.name,
                        type(exc).__name__, exc)
            time.sleep(2)
    return output


def run_cell_notebook(study_file: str, cell: CellSpec, output: str, timeout: int, env: dict[str, str]) -> float:
    """One cell of the grid as a worker runs it (a local process or a Dask worker): `ablation_cell.ipynb` through
    papermill into `output`, in a kernel that inherits `env` (`monolib.study.cluster.task_environment`: the client's
    runs folder and device): the worker's warm kernel (`monolib.study.kernels`) unless ``MONOLIB_KERNELS=cold``.
    Returns its wall seconds."""
    t0 = time.perf_counter()
    if cluster.FINGERPRINT_ENV in env:  # a Dask worker: still the client's code, libraries and study, now?
        cluster.check_fingerprint(study_file, env[cluster.FINGERPRINT_ENV])
        env = {k: v for k, v in env.items() if k != cluster.FINGERPRINT_ENV}
    os.environ.update(env)
    execute(CELL_NOTEBOOK, Path(output), {"study": study_file, "method": cell.method, "scenario": cell.scenario,
                                          "threshold": float(cell.threshold), "seed": int(cell.seed), "out_dir": "",
                                          "fold": -1 if cell.fold is None else int(cell.fold)},
            timeout, warm=kernels.warm_enabled(), env=env)
    return time.perf_counter() - t0

