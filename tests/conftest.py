"""Shared pytest fixtures, and how `make test` shares the tests between its processes (`group_of`)."""
import functools
import os
import subprocess
import sys
from pathlib import Path

import pytest

from monolib import paths


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


# `make test` runs pytest on two processes (pytest-xdist, `-n 2`), a file at a time per process. The files that write
# into the checkout's runs/ folder (the smoke study, its figures, the notebooks that read and draw them) run on one
# process, one after another in file order as without xdist: their group is "runs". The files that only read the
# smoke study's cells and inputs (a Dask cluster's cells and warm kernels compared with them, into folders of their
# own) form a second group, and every other file works in a temporary folder of its own.
WRITES_RUNS = ("smoke_study", "paths.study_dir", "paths.figures_dir", "paths.cell_dir", "monolib.cli",
               "paths.NOTEBOOKS", "papermill")
READS_SMOKE_CELLS = ("tests/test_cluster.py", "tests/test_kernels.py")


def group_of(path: str) -> str:
    """The xdist work unit of a test file (a path relative to the checkout, as in a node id)."""
    if path in READS_SMOKE_CELLS:
        return "smoke cells"
    if path.startswith("notebooks/") or any(word in _text(paths.ROOT / path) for word in WRITES_RUNS):
        return "runs"
    return path


@functools.lru_cache(maxsize=None)
def _text(path: Path) -> str:
    return path.read_text() if path.suffix == ".py" and path.is_file() else ""


def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScopeScheduling

    class ByGroup(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return group_of(nodeid.split("::", 1)[0])

    return ByGroup(config, log)
