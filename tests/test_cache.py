"""Nothing wrong is ever cached: missing predictions stop the graph stage, caches know the code that made them,
corrupt cached files are recomputed, and a seed gives the same weights.

Runs on the smoke study's mini-Hypersim (rendered once per session), with `runs/` in a temporary folder.
"""
import ast
import dataclasses
import logging
import shutil

import numpy as np
import pytest
import torch

from monolib import io, paths, versions
from monolib.data import dataset, selection
from monolib.graphs import scenegraphs
from monolib.params import load_study
from monolib.perception import predictions
from monolib.report import graph_sizes
from monolib.retrieval import cell


@pytest.fixture
def study(smoke_dataset, tmp_path, monkeypatch):
    """The smoke study on the session's rendered dataset, with its runs/ under tmp_path."""
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    s = load_study("smoke")
    return dataclasses.replace(s, name="cache_test", dataset=dataclasses.replace(s.dataset, root=str(smoke_dataset)))


def frames_of(s):
    ds = dataset.open_dataset(s)
    return selection.select_frames(s, ds, s.gcn.val_settings).all()


def fake_predictions(s, name="deeplab"):
    """Write a complete set of predictions of the segmentation model (the ground truth, in the real file format)
    with its metrics and marker, as the perception stage leaves them."""
    frames = frames_of(s)
    for f in frames:
        io.write_h5(predictions.prediction_path(s, name, f), f.semantic.astype(np.int16))
    io.write_json(predictions.model_dir(s, name) / "metrics.json", {"pixel_accuracy": 1.0, "miou": 1.0})
    io.write_json(predictions.predictions_dir(s, name) / "_complete.json", {"frames": sorted(f.key for f in frames)})
    return frames


# ---- missing predictions are an error, never empty graphs ------------------------------------------------------

def test_missing_predictions_stop_the_graph_stage_and_cache_nothing(study):
    with pytest.raises(predictions.PredictionsMissing) as err:
        scenegraphs.load(study, "s2")  # GT depth, DeepLabV3 semantics: perception has not run
    msg = str(err.value)
    assert "'deeplab'" in msg and "monolib perception" in msg
    assert not scenegraphs.graphs_path(study, "s2").exists()
    assert not list((study.data_dir / "graphs").glob("*.pt")) if (study.data_dir / "graphs").exists() else True


def test_a_truncated_prediction_is_an_error_and_is_predicted_again(study):
    frames = fake_predictions(study)
    assert predictions._complete(study, "deeplab", frames)
    bad = predictions.prediction_path(study, "deeplab", frames[3])
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(predictions.PredictionsMissing) as err:
        scenegraphs.load(study, "s2")
    assert str(bad) in str(err.value) and "'deeplab'" in str(err.value)
    assert not scenegraphs.graphs_path(study, "s2").exists()  # nothing cached
    assert not bad.exists()  # removed: the perception stage predicts that frame again
    assert not predictions._complete(study, "deeplab", frames)


def test_predictions_complete_give_graphs(study):
    fake_predictions(study)
    graphs = scenegraphs.load(study, "s2")
    assert sum(len(v) for v in graphs.values()) == len(frames_of(study))
    assert sum(g.num_nodes for g in graphs["test"]) > 0


def test_a_missing_file_of_a_download_is_an_empty_graph_counted_in_graph_sizes(study, tmp_path):
    root = tmp_path / "download"
    shutil.copytree(study.dataset.root, root)
    s = dataclasses.replace(study, dataset=dataclasses.replace(study.dataset, root=str(root)),
                            scenarios={"s1": study.scenarios["s1"]})
    f = frames_of(s)[0]
    f.files["semantic"].unlink()
    data = scenegraphs.load_file(s, "s1")
    assert len(data["missing"]) == 1 and f.key in data["missing"][0]
    table = graph_sizes.graph_sizes(s)
    assert set(table[table.scenario == "s1"].missing_frames) == {1}
    assert "missing or unreadable file of the dataset** (each is an empty graph in every threshold): s1 1" in \
        graph_sizes.graph_sizes_markdown(table)


def test_a_cell_key_holds_the_frames_the_graph_stage_could_not_read(study, tmp_path):
    """The graphs of a download with a file lost are other graphs (an empty one for that frame): the cells
    on them have another key, though every upstream key is the same."""
    one = {"s1": study.scenarios["s1"]}
    whole = dataclasses.replace(study, scenarios=one)
    root = tmp_path / "download"
    shutil.copytree(study.dataset.root, root)
    broken = dataclasses.replace(study, name="cache_test_broken", scenarios=one,
                                 dataset=dataclasses.replace(study.dataset, root=str(root)))
    frames_of(broken)[2].files["depth_meters"].unlink()
    assert scenegraphs.scenario_key(broken, "s1") == scenegraphs.scenario_key(whole, "s1")
    unbuilt = cell.cell_key(whole, "gcn", "s1", 1.0, 0)  # (graphs not built: nothing known unread)
    assert scenegraphs.load_file(whole, "s1")["missing"] == []
    assert len(scenegraphs.load_file(broken, "s1")["missing"]) == 1
    assert cell.cell_key(whole, "gcn", "s1", 1.0, 0) == unbuilt
    assert cell.cell_key(broken, "gcn", "s1", 1.0, 0) != unbuilt
    assert cell.graph_inputs(whole, "s1") == scenegraphs.scenario_key(whole, "s1")


# ---- corrupt cached files are recomputed -------------------------------------------------------------------

def test_a_graphs_file_cut_in_half_is_rebuilt_with_a_warning(study, caplog):
    first = scenegraphs.load(study, "s1")
    path = scenegraphs.graphs_path(study, "s1")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with caplog.at_level(logging.WARNING):
        again = scenegraphs.load(study, "s1")
    assert str(path) in caplog.text and "recomputed" in caplog.text
    assert [g.frame for g in again["test"]] == [g.frame for g in first["test"]]
    assert all(torch.equal(a.x, b.x) for a, b in zip(again["test"], first["test"]))


@pytest.mark.parametrize("content", [b'{"method": "gcn", "metr', b"", b"[1, 2]", b'{"method": "gcn"}'])
def test_a_cell_record_cut_short_makes_the_cell_incomplete(tmp_path, caplog, content):
    (tmp_path / "cell.json").write_bytes(content)
    with caplog.at_level(logging.WARNING):
        assert not cell.is_complete(tmp_path)
    assert "cell.json" in caplog.text
    assert not (tmp_path / "cell.json").exists()


def test_a_cell_of_other_inputs_is_not_complete(tmp_path):
    io.write_json(tmp_path / "cell.json", {"method": "gcn", "metrics": {}, "key": "old"})
    assert cell.is_complete(tmp_path)  # no key asked: a readable record
    assert cell.is_complete(tmp_path, "old")
    assert not cell.is_complete(tmp_path, "new")


def test_truncated_weights_are_removed_and_reported(tmp_path, caplog):
    from monolib.perception import segmentation as seg

    spec = load_study("smoke").perception.segmentation
    path = tmp_path / "model.pt"
    seg.save_model(seg.build_model(spec), path)
    assert io.load_cached(path, lambda p: seg.load_model(spec, p)) is not None
    path.write_bytes(path.read_bytes()[:1000])
    with caplog.at_level(logging.WARNING):
        assert io.load_cached(path, lambda p: seg.load_model(spec, p), "weights of deeplab") is None
    assert "weights of deeplab" in caplog.text and not path.exists()


@pytest.mark.parametrize("failure", [
    PermissionError(13, "Permission denied"),
    OSError(5, "Input/output error"),
    OSError(116, "Stale file handle"),
    RuntimeError("CUDA out of memory. Tried to allocate 2.00 GiB"),
    RuntimeError("Attempting to deserialize object on a CUDA device but torch.cuda.is_available() is False"),
])
def test_a_failure_outside_the_file_removes_nothing(tmp_path, failure):
    """Valid weights that cannot be read here (no permission, an I/O error, a stale network handle, the device out of
    memory): one clear error naming the file, and the file is still there (a reader never removes a
    model it cannot open: it may be someone else's)."""
    from monolib.perception import segmentation as seg

    spec = load_study("smoke").perception.segmentation
    path = tmp_path / "model.pt"
    seg.save_model(seg.build_model(spec), path)
    before = path.read_bytes()

    def read(p):
        seg.load_model(spec, p)  # the real reader runs, then the failure of the environment
        raise failure

    with pytest.raises(io.CacheUnreadable, match=str(path)):
        io.load_cached(path, read, "weights of deeplab")
    assert path.read_bytes() == before


def test_a_file_without_read_permission_is_an_error_and_is_kept(tmp_path, monkeypatch):
    """`chmod 000` as a user without the right to read it: root reads anyway, so the permission check is made to
    answer as it would for that user."""
    path = tmp_path / "cell.json"
    path.write_text('{"metrics": {}, "method": "gcn"}')
    path.chmod(0)
    monkeypatch.setattr(io.os, "access", lambda p, mode: False)
    try:
        with pytest.raises(io.CacheUnreadable, match="no permission to read it"):
            io.load_cached(path, io.read_json_dict, "cell record")
        assert path.exists()
    finally:
        path.chmod(0o644)


# ---- caches know their code ------------------------------------------------------------------------------------

def test_source_version_ignores_comments_and_docstrings_but_not_code():
    src = (paths.PACKAGE / "graphs" / "build.py").read_text()
    v = versions.source_version(src)
    assert versions.source_version('"""Another docstring."""\n' + src.split('"""', 2)[2]) == v
    assert versions.source_version(src.replace("\n\n", "\n\n# a comment\n", 1)) == v
    tree = ast.parse(src)
    assert versions.source_version(ast.unparse(tree)) == v  # layout only
    const = next(n for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, (int, float))
                 and not isinstance(n.value, bool) and n.value not in (0, 1))
    const.value = const.value * 2 + 1  # one constant of the graph builder changed
    assert versions.source_version(ast.unparse(tree)) != v


def test_a_changed_graph_builder_gives_new_graph_and_cell_keys_only(study, monkeypatch):
    before = {"model": predictions.model_key(study, "deeplab"), "graphs": scenegraphs.scenario_key(study, "s1"),
              "cell": cell.cell_key(study, "gcn", "s1", 1.0, 0), "data": dataset.dataset_key(study)}
    real = versions.module_version
    monkeypatch.setattr(versions, "module_version",
                        lambda m: real(m) + ("-changed" if m == "graphs.build" else ""))
    versions.code_version.cache_clear()
    try:
        after = {"model": predictions.model_key(study, "deeplab"), "graphs": scenegraphs.scenario_key(study, "s1"),
                 "cell": cell.cell_key(study, "gcn", "s1", 1.0, 0), "data": dataset.dataset_key(study)}
    finally:
        versions.code_version.cache_clear()
    assert after["graphs"] != before["graphs"] and after["cell"] != before["cell"]
    assert after["model"] == before["model"] and after["data"] == before["data"]


def test_keys_hold_the_device_and_the_deterministic_mode(study):
    other = dataclasses.replace(study, deterministic=False)
    assert predictions.model_key(other, "deeplab") != predictions.model_key(study, "deeplab")
    assert cell.cell_key(other, "gcn", "s1", 1.0, 0) != cell.cell_key(study, "gcn", "s1", 1.0, 0)


def _module_file(module: str):
    """The module's file (`versions.module_file`); None when there is none."""
    f = versions.module_file(module)
    return f if f.is_file() else None


def _monolib_imports(module: str) -> set[str]:
    """The monolib modules `module` imports, named relative to the package (``data.synth``, ``paths``)."""
    tree = ast.parse(_module_file(module).read_text())
    out = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom) and n.module and n.module.split(".")[0] == "monolib":
            base = n.module.split(".")[1:]
            for a in n.names:  # `from monolib.data import synth` names a module; `from monolib.io import x` does not
                out.add(".".join(base + [a.name]) if _module_file(".".join(base + [a.name])) else ".".join(base))
        elif isinstance(n, ast.Import):
            out |= {a.name.split(".", 1)[1] for a in n.names if a.name.startswith("monolib.")}
    return out - {""}


@pytest.mark.parametrize("stage", list(versions.STAGE_MODULES))
def test_every_module_a_stage_computes_with_is_in_its_version(stage):
    """A stage's output can only change with the code of its modules: each of their monolib imports is in the
    stage's list, an upstream stage's (keyed), or infrastructure / presentation (`monolib.versions`)."""
    allowed = set(versions.STAGE_MODULES[stage]) | set(versions.INFRASTRUCTURE) | set(versions.PRESENTATION)
    for up in versions.UPSTREAM[stage]:
        allowed |= set(versions.STAGE_MODULES[up])
    for m in versions.STAGE_MODULES[stage]:
        assert _module_file(m), m
        assert _monolib_imports(m) <= allowed, (m, sorted(_monolib_imports(m) - allowed))


# ---- deterministic mode ----------------------------------------------------------------------------------------

def test_the_same_seed_gives_the_same_weights_and_sets_deterministic_kernels(study):
    from monolib.graphs import build as graph
    from monolib.retrieval import gcn

    graphs = {k: [graph.at_threshold(g, 2.0) for g in v] for k, v in scenegraphs.load(study, "s1").items()}
    spec = dataclasses.replace(study.gcn, epochs=2)
    a = gcn.train(graphs["train"], graphs["val"], spec, seed=3, threads=1).model.state_dict()
    assert torch.are_deterministic_algorithms_enabled() and torch.backends.cudnn.deterministic
    b = gcn.train(graphs["train"], graphs["val"], spec, seed=3, threads=1).model.state_dict()
    c = gcn.train(graphs["train"], graphs["val"], spec, seed=4, threads=1).model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], c[k]) for k in a)


def test_committed_studies_are_deterministic():
    for f in paths.study_files():
        assert load_study(str(f), check_files=False).deterministic, f.name


def test_the_same_weights_saved_twice_are_the_same_bytes(tmp_path):
    """`io.save_torch` writes through a temporary file, whose name must not reach the file (torch names the archive
    inside after a path it is given): a cell's model.pt and a shipped zoo file's sha256 depend on the weights alone."""
    from monolib import io

    state = {"w": torch.arange(6.0).reshape(2, 3)}
    io.save_torch(tmp_path / "a.pt", state)
    io.save_torch(tmp_path / "b.pt", state)
    assert (tmp_path / "a.pt").read_bytes() == (tmp_path / "b.pt").read_bytes()
    assert torch.equal(torch.load(tmp_path / "a.pt")["w"], state["w"])
    assert not list(tmp_path.glob(".*.tmp"))
