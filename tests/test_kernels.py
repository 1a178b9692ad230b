"""Warm kernels (monolib.study.kernels): a cell's files do not depend on whether its notebook ran in a warm kernel or in
a kernel of its own, nor on which cells ran before it in that kernel; a kernel killed during a cell is replaced and
the cell run again."""
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import nbformat
import pytest

from monolib import paths
from monolib.study import kernels

pytestmark = [pytest.mark.slow, pytest.mark.reads_smoke_cells]
CELL_FILES = ("cell.json", "rankings.csv", "protocol.csv", "embeddings.npy", "model.pt", "history.csv")


def same_cell_files(a: Path, b: Path, ignore: tuple = ()) -> list[str]:
    """The files of two cell folders compared byte for byte (cell.json without its wall-clock `timings` and the
    keys in `ignore`)."""
    differ = []
    for name in CELL_FILES:
        fa, fb = a / name, b / name
        if fa.exists() != fb.exists():
            differ.append(f"{name}: only in one")
        elif name == "cell.json":
            ja, jb = json.loads(fa.read_text()), json.loads(fb.read_text())
            for j in (ja, jb):
                for key in ("timings", *ignore):
                    j.pop(key, None)
            if ja != jb:
                differ.append(name)
        elif fa.exists() and fa.read_bytes() != fb.read_bytes():
            differ.append(name)
    return differ


def test_warm_and_cold_kernels_give_the_same_files(smoke_study, tmp_path):
    """A cell of the smoke study's grid (run in a warm kernel by the session's `monolib study smoke`) run again in
    a kernel of its own (`--cold-kernels`) into another runs folder that holds the same dataset, models and graphs,
    through a study file that is the smoke study at one threshold and scenario (s2 at 2 m: predicted semantics):
    the cell's files are the same bytes (cell.json but for its wall-clock timings, the study file's path and the
    mark of a cell copied from a smaller threshold)."""
    runs = tmp_path / "runs"
    shutil.copytree(paths.study_dir("smoke"), runs / "smoke",
                    ignore=lambda d, names: [n for n in names if Path(d) == paths.study_dir("smoke")
                                             and n in ("cells", "notebooks", "figures")])
    subset = tmp_path / "smoke_subset.yaml"
    subset.write_text("name: smoke\nextends: smoke\nthresholds: [2]\nscenarios: {s1: null, s3: null, s4: null}\n")
    env = {**os.environ, "MPLBACKEND": "agg", "MONOLIB_RUNS": str(runs), "MONOLIB_FIGURES": str(tmp_path / "fig")}
    out = subprocess.run([sys.executable, "-m", "monolib.cli", "study", str(subset), "--cold-kernels"], env=env,
                         capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    cold = sorted((runs / "smoke" / "cells").glob("*/*/cell.json"))
    assert len(cold) == 1
    for c in cold:
        w = paths.study_dir("smoke") / c.parent.relative_to(runs / "smoke")
        assert w.is_dir(), w
        # the session's grid may have copied a cell from threshold 0 with the same graphs (`same_graphs_as`), where
        # this grid of one threshold computes it: the same numbers either way
        ignore = ("study_file", "same_graphs_as")
        assert not same_cell_files(w, c.parent, ignore=ignore), (w, same_cell_files(w, c.parent, ignore=ignore))


def run_cell(cell: tuple, out: Path) -> None:
    from monolib.study.notebooks import CELL_NOTEBOOK, execute

    method, scenario, threshold, seed = cell
    execute(CELL_NOTEBOOK, out / "cell.ipynb", {"study": "smoke", "method": method, "scenario": scenario,
                                                "threshold": threshold, "seed": seed, "out_dir": str(out)},
            timeout=600, warm=True, env={"MPLBACKEND": "agg"})


def test_a_cell_does_not_depend_on_the_cells_before_it(smoke_study, tmp_path):
    """One cell run in a warm kernel after two different predecessors (another scenario and threshold; an image
    method with another seed): the same files both times, and the same as the study's own cell."""
    target = ("gcn", "s1", 1.0, 0)
    kernels.discard()
    try:
        run_cell(("gcn", "s3", 2.0, 0), tmp_path / "a")
        pid_a = kernels._local.kernel.pid()
        run_cell(target, tmp_path / "after_a")
        assert kernels._local.kernel.pid() == pid_a  # the same kernel ran both
        kernels.discard()
        run_cell(("gcn", "s2", 0.0, 1), tmp_path / "b")
        run_cell(target, tmp_path / "after_b")
    finally:
        kernels.discard()
    assert not same_cell_files(tmp_path / "after_a", tmp_path / "after_b")
    assert not same_cell_files(tmp_path / "after_a", paths.cell_dir("smoke", *target))


def test_a_kernel_killed_during_a_cell_is_replaced_and_the_cell_run_again(tmp_path):
    """The first run of a notebook kills its own kernel half-way (SIGKILL, from outside): the runner discards the
    dead kernel, runs the notebook again in a fresh one, and it completes there."""
    from monolib.study.notebooks import execute

    marker = tmp_path / "pid"
    nb = nbformat.v4.new_notebook()
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb.cells = [nbformat.v4.new_code_cell(f'marker = "{marker}"', metadata={"tags": ["parameters"]}),
                nbformat.v4.new_code_cell("import os, pathlib, time\np = pathlib.Path(marker)\n"
                                          "first = not p.exists()\np.write_text(str(os.getpid()))\n"
                                          "time.sleep(60 if first else 0)\nprint('done in', os.getpid())")]
    path = tmp_path / "sleepy.ipynb"
    nbformat.write(nb, path)
    kernels.discard()
    result = {}

    def run():
        try:
            execute(path, tmp_path / "out.ipynb", {"marker": str(marker)}, timeout=120, warm=True, env={})
            result["ok"] = True
        except Exception as exc:  # noqa: BLE001 - reported by the assertion below
            result["error"] = exc
        finally:
            kernels.discard()  # this thread's kernel

    worker = threading.Thread(target=run)
    worker.start()
    deadline = time.time() + 60
    while not marker.exists() and time.time() < deadline:
        time.sleep(0.2)
    first_pid = int(marker.read_text())
    os.kill(first_pid, signal.SIGKILL)
    worker.join(180)
    try:
        assert result.get("ok"), result
        out = nbformat.read(tmp_path / "out.ipynb", 4)
        text = out.cells[-1].outputs[0]["text"]
        assert text.startswith("done in") and int(text.split()[-1]) != first_pid
    finally:
        kernels.discard()


def test_the_switch_keeps_a_kernel_per_cell(monkeypatch):
    monkeypatch.setenv("MONOLIB_KERNELS", "cold")
    assert not kernels.warm_enabled()
    monkeypatch.setenv("MONOLIB_KERNELS", "warm")
    assert kernels.warm_enabled()
    monkeypatch.setenv("MONOLIB_KERNELS", "tepid")
    with pytest.raises(ValueError, match="MONOLIB_KERNELS"):
        kernels.warm_enabled()


def test_a_cycle_frozen_by_a_reset_is_collected_within_the_full_collection_period(monkeypatch):
    """`reset_kernel` freezes what survives it (the next collections skip it); every `FULL_COLLECTION_EVERY`
    resets it unfreezes first, so a reference cycle that a kept cache let go of is not kept for the kernel's life.
    Outside a kernel IPython's reset (its collection of the last notebook's objects) is not there: the test collects
    after each reset instead."""
    import gc
    import weakref

    class Node:
        pass

    monkeypatch.setattr(kernels, "_start_state", {})
    node = Node()
    node.self = node
    alive = weakref.ref(node)
    cache = [node]
    del node
    try:
        kernels.reset_kernel(False)  # the kernel's first reset: records its state, freezes the cycle with the rest
        cache.clear()
        for _ in range(kernels.FULL_COLLECTION_EVERY - 1):
            kernels.reset_kernel(True)
            gc.collect()
        assert alive() is not None  # frozen: the collections do not see it
        kernels.reset_kernel(True)
        gc.collect()
        assert alive() is None
    finally:
        gc.unfreeze()
