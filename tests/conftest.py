"""Shared pytest fixtures."""
import os
import subprocess
import sys

import pytest


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
