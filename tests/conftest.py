"""Shared pytest fixtures."""
import pytest


@pytest.fixture(scope="session")
def smoke_dataset(tmp_path_factory):
    """The smoke study's mini-Hypersim, rendered once per test session (monolib.synth); returns its root Path."""
    from monolib import params, synth

    study = params.load_study("smoke")
    root = tmp_path_factory.mktemp("smoke_synth") / "dataset"
    return synth.render_dataset(study, root, progress=False)
