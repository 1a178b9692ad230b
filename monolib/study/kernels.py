"""Warm notebook kernels: each worker of the grid keeps one Jupyter kernel alive and papermill executes its cells'
notebooks in it one after the other, instead of paying for a new Python process and its imports (torch,
torch_geometric, monolib: about 10 s) per cell.

* `WarmKernelEngine`: a papermill engine (``engine_name="monolib_warm"``) that executes a notebook in an
  already-started kernel through that kernel's client (nbclient's ``km`` and ``kc``), leaving both alive. One
  client per kernel, connected once: a new client's `wait_for_ready` waits 0.2 s on a silent IOPub channel, and each
  cell took two of them (the reset and the notebook), about half of a warm cell's overhead.
* `kernel(cwd, env, config)`: this worker thread's kernel, started on first use; replaced when it died, or when the
  environment a task asks for (``MONOLIB_*``: the runs folder, the device) is not the one it was started with,
  because `monolib.paths` reads it at import.
* Before each notebook the kernel is reset (`reset_kernel`, run inside it): the user namespace emptied, the working
  directory, environment variables and matplotlib's figures and rcParams put back as they were when the kernel
  started, and every ``functools`` cache of monolib's modules cleared. Everything else that decides a result (seeds,
  torch threads, deterministic mode) is set by the cell itself (`monolib.retrieval.cell.run_cell`), so the result of a
  cell does not depend on the cells that ran before it in the same kernel (`tests/test_kernels.py`).
* `discard()`: shut the kernel down; `monolib.study.notebooks.execute` does so after a notebook error, a timeout
  or a dead kernel, so a cell never inherits a broken kernel (and the cell is re-run once in a fresh one when the
  kernel, not the notebook, failed).

``MONOLIB_KERNELS=cold`` (or ``monolib study ... --cold-kernels``) keeps the kernel-per-cell behaviour.
"""
from __future__ import annotations

import logging
import os
import threading
from typing import Optional

from monolib import versions

log = logging.getLogger(__name__)
ENGINE = "monolib_warm"
_local = threading.local()  # one kernel per worker thread (a local process, or a Dask worker's thread)
_start_state: dict = {}     # inside a kernel: what `reset_kernel` restores
FULL_COLLECTION_EVERY = 32  # resets between two collections over every object of the kernel (`reset_kernel`)


def warm_enabled() -> bool:
    """Warm kernels unless ``MONOLIB_KERNELS=cold``."""
    choice = os.environ.get("MONOLIB_KERNELS", "warm").lower()
    if choice not in ("warm", "cold"):
        raise ValueError(f"MONOLIB_KERNELS: expected warm or cold, got {choice!r}")
    return choice == "warm"


def _engine():
    from papermill.clientwrap import PapermillNotebookClient
    from papermill.engines import NBClientEngine, papermill_engines
    from papermill.utils import remove_args

    class WarmKernelEngine(NBClientEngine):
        """nbclient's execution in the kernel of `km` (given by the caller, started and kept by it)."""

        @classmethod
        def execute_managed_notebook(cls, nb_man, kernel_name, log_output=False, stdout_file=None,
                                     stderr_file=None, start_timeout=60, execution_timeout=None, **kwargs):
            km, kc = kwargs.pop("km"), kwargs.pop("kc")
            kwargs = remove_args(["input_path", "timeout", "startup_timeout"], **kwargs)
            client = PapermillNotebookClient(nb_man, km=km, timeout=execution_timeout, startup_timeout=start_timeout,
                                             kernel_name=kernel_name, log=logging.getLogger("papermill"),
                                             log_output=log_output, stdout_file=stdout_file,
                                             stderr_file=stderr_file, **kwargs)
            client.kc = kc  # the kernel's own client, already connected: nbclient starts none of its own
            return client.execute()

    if ENGINE not in papermill_engines._engines:
        papermill_engines.register(ENGINE, WarmKernelEngine)
    return ENGINE


class Kernel:
    """A started kernel with the environment it was started in. Its manager is jupyter_client's asynchronous one,
    as nbclient's own: with a blocking client, nbclient's wait for output would block the event loop that checks
    whether the kernel is still alive, and a killed kernel would hang the cell instead of failing it."""

    def __init__(self, cwd: str, env: dict[str, str], config):
        from jupyter_client.manager import AsyncKernelManager
        from jupyter_core.utils import run_sync

        self.env = dict(env)
        self.km = AsyncKernelManager(kernel_name="python3", config=config)
        run_sync(self.km.start_kernel)(cwd=cwd, env={**os.environ, **env},
                                       extra_arguments=["--IPKernelApp.log_level=CRITICAL"])
        self.kc = self.km.client()  # kept for the kernel's life: the resets and every notebook (`WarmKernelEngine`)
        self.kc.start_channels()
        try:
            run_sync(self.kc.wait_for_ready)(timeout=60)
        except Exception:
            self.shutdown()
            raise
        self.kc.allow_stdin = False
        self.cells = 0

    def alive(self) -> bool:
        from jupyter_core.utils import run_sync

        return bool(run_sync(self.km.is_alive)())

    def pid(self) -> int:
        return self.km.provisioner.process.pid

    def run(self, code: str, timeout: float = 60) -> None:
        """Execute `code` in the kernel and wait for it; RuntimeError with the kernel's error when it fails."""
        from jupyter_core.utils import run_sync

        reply = run_sync(self.kc.execute_interactive)(code, timeout=timeout, store_history=False,
                                                      output_hook=lambda msg: None)
        if reply["content"]["status"] != "ok":
            raise RuntimeError(f"warm kernel: {reply['content'].get('ename')}: {reply['content'].get('evalue')}")

    def shutdown(self) -> None:
        from jupyter_core.utils import run_sync

        if getattr(self, "kc", None) is not None:
            self.kc.stop_channels()
        try:
            run_sync(self.km.shutdown_kernel)(now=True)
        except Exception as exc:  # a kernel that is already gone
            log.debug("warm kernel shutdown: %s", exc)


def kernel(cwd: str, env: dict[str, str], config) -> Kernel:
    """This thread's warm kernel, reset for the next notebook (`reset_kernel`): started on first use, replaced when
    it is not alive or was started with another environment than `env`."""
    k: Optional[Kernel] = getattr(_local, "kernel", None)
    if k is not None and (not k.alive() or k.env != dict(env)):
        discard()
        k = None
    if k is None:
        k = Kernel(cwd, env, config)
        _local.kernel = k
        import atexit

        atexit.register(k.shutdown)
        try:
            from multiprocessing import util

            util.Finalize(k, Kernel.shutdown, args=(k,), exitpriority=10)  # a pool worker's exit skips atexit
        except Exception:  # noqa: BLE001 - not in a multiprocessing worker
            pass
    k.run(f"__import__('monolib.study.kernels').study.kernels.reset_kernel({k.cells > 0!r})")
    k.cells += 1
    return k


def discard() -> None:
    """Shut this thread's warm kernel down (after a failure: the next notebook gets a fresh one)."""
    k: Optional[Kernel] = getattr(_local, "kernel", None)
    _local.kernel = None
    if k is not None:
        k.shutdown()


def reset_kernel(used: bool) -> None:
    """Run inside a warm kernel before each notebook. The first time (`used` False) it records the kernel's starting
    state; afterwards it restores it: the user namespace emptied, the working directory and environment variables
    as at the start, matplotlib's figures closed and rcParams restored, every functools cache of monolib cleared.
    Kept: the source hashes of `monolib.versions.file_version` (keyed by each file's modification time and size),
    and the graphs files this kernel has read (`monolib.graphs.scenegraphs._READ`, by path, inode, mtime and size: a
    file's content, never stale), so that a scenario's cells in a row read its file once."""
    import functools
    import gc
    import sys

    import matplotlib

    if not used or not _start_state:
        _start_state.update(cwd=os.getcwd(), environ=dict(os.environ), rc=matplotlib.rcParams.copy())
        gc.freeze()
        return
    from IPython import get_ipython

    os.chdir(_start_state["cwd"])
    os.environ.clear()
    os.environ.update(_start_state["environ"])
    if "matplotlib.pyplot" in sys.modules:
        sys.modules["matplotlib.pyplot"].close("all")
    matplotlib.rcParams.update(_start_state["rc"])
    for name, module in list(sys.modules.items()):
        if name == "monolib" or name.startswith("monolib."):
            for value in list(vars(module).values()):
                if isinstance(value, functools._lru_cache_wrapper) and value is not versions.file_version:
                    value.cache_clear()  # (file_version: keyed by each file's mtime and size, never stale)
    _start_state["resets"] = _start_state.get("resets", 0) + 1
    if _start_state["resets"] % FULL_COLLECTION_EVERY == 0:
        gc.unfreeze()  # now and then one collection walks everything, so no cycle among them is kept
        gc.collect()
    ip = get_ipython()
    if ip is not None:
        ip.reset(new_session=False)  # (its full garbage collection: of what the last notebook left)
    # What survives a reset (modules, the kept caches) is moved out of the collector's sight, so that the next
    # reset's collection walks only the next notebook's objects: a fifth of a second a cell with torch and PyG
    # loaded. The frozen objects are still freed by their reference counts; a cycle among them that a cache let go
    # of waits for the next full collection (`FULL_COLLECTION_EVERY` resets).
    gc.freeze()


def execute(notebook: str, output: str, parameters: dict, timeout: int, cwd: str, env: dict[str, str],
            config) -> None:
    """papermill's execution of `notebook` in this thread's warm kernel (`kernel`)."""
    import papermill

    k = kernel(cwd, env, config)
    papermill.execute_notebook(notebook, output, parameters=parameters, kernel_name="python3", cwd=cwd,
                               execution_timeout=timeout, progress_bar=False, log_output=False,
                               engine_name=_engine(), km=k.km, kc=k.kc)
