"""Shared pytest fixtures, and how `make test` shares the tests between its processes (`group_of`)."""
import ast
import functools
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def pytest_configure(config):
    """Each worker process of `make test` (pytest-xdist) computes on one thread, and so do the processes it starts
    unless a study sets its own: two workers on two cores, each with torch's default of a thread per core,
    oversubscribe them, and a training step then waits on threads that are not running (the zoo's resume test took
    11 s alone and 64 s beside the other worker)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        os.environ["OMP_NUM_THREADS"] = "1"
        import torch

        torch.set_num_threads(1)


@pytest.fixture(scope="session")
def smoke_dataset(tmp_path_factory):
    """The smoke study's mini-Hypersim, rendered once per test session (monolib.data.synth); returns its root Path."""
    from monolib import params
    from monolib.data import synth

    study = params.load_study("smoke")
    root = tmp_path_factory.mktemp("smoke_synth") / "dataset"
    return synth.render_dataset(study, root, progress=False)


@pytest.fixture(scope="session")
def smoke_study():
    """`monolib study smoke`, as `make smoke` runs it (cached stages make a second session cheap); the local path
    that `tests/test_cluster.py` compares a Dask cluster's cells with."""
    out = subprocess.run([sys.executable, "-m", "monolib.cli", "study", "smoke"], cwd="/",
                         env={**os.environ, "MPLBACKEND": "agg"}, capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out


# `make test` runs pytest on two processes (pytest-xdist), a group of tests at a time per process. A test file that
# reads or writes the checkout's runs/ folder (the smoke study, its figures, the notebooks that read and draw them)
# says so with its module marker `pytestmark = pytest.mark.shares_runs`: those files run on one process, one after
# another in file order as without xdist. The files marked `reads_smoke_cells` only read the smoke study's cells and
# inputs (a Dask cluster's cells and warm kernels compared with them, into folders of their own): a second group.
# The notebooks under nbval run at their defaults, on the smoke study: in the first group. Every other file works in
# a temporary folder of its own and is a group by itself (its module fixtures computed once).
# xdist's scheduler sees node ids, not markers, so the groups are read from each file's `pytestmark` statement
# (`markers_of`), and `pytest_collection_modifyitems` checks, in each process, that every test carries exactly its
# file's group marker. (xdist's own `--dist loadgroup` cannot be used: pytest 9 ignores the group suffix that
# xdist 3.8 writes into a test's node id, and every test would run wherever a process is free.)
GROUPS = {"shares_runs": "runs", "reads_smoke_cells": "smoke cells"}


@functools.lru_cache(maxsize=None)
def markers_of(path: str) -> frozenset:
    """The names `X` of the `pytest.mark.X` in the module-level ``pytestmark = ...`` of a test file (relative to the
    checkout); empty for a file without one, or not a Python file."""
    file = ROOT / path
    if file.suffix != ".py" or not file.is_file():
        return frozenset()
    names = set()
    for node in ast.parse(file.read_text(), str(file)).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets):
            names |= {n.attr for n in ast.walk(node.value) if isinstance(n, ast.Attribute)
                      and isinstance(n.value, ast.Attribute) and n.value.attr == "mark"}
    return frozenset(names)


def group_of(path: str) -> str:
    """The xdist work unit of a test file (a path relative to the checkout, as in a node id)."""
    if path.startswith("notebooks/"):
        return GROUPS["shares_runs"]
    marked = [group for marker, group in GROUPS.items() if marker in markers_of(path)]
    return marked[0] if marked else path


def pytest_collection_modifyitems(items):
    """A group marker on a single test, or a file's marker missing from one of its tests, would put that test in the
    wrong process: refused."""
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        wanted = {m for m in GROUPS if m in markers_of(path)}
        if {m for m in GROUPS if item.get_closest_marker(m) is not None} != wanted:
            raise pytest.UsageError(f"{item.nodeid}: the markers {', '.join(GROUPS)} belong in its file's "
                                    f"module-level `pytestmark` (tests/conftest.py, `group_of`), not on one test")


def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling

    class ByGroup(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return group_of(nodeid.split("::", 1)[0])

    return ByGroup(config, log)
