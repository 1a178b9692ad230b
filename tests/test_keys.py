"""Each stage's key holds exactly what decides its output: every change below that should not matter (a name, a
label, a path, a worker count, the k of the metrics) keeps the key, and every change that should gives a new one.
(The keys: `dataset.dataset_key`, `predictions.model_key`, `scenegraphs.scenario_key`, `cell.cell_key`.)"""
import copy
import json
import shutil

import pytest
import torch

from monolib import paths, versions
from monolib.data import dataset
from monolib.graphs import scenegraphs
from monolib.params import load_study
from monolib.perception import predictions
from monolib.retrieval import cell

pytestmark = pytest.mark.shares_runs


BASE = load_study("smoke")


def study():
    return copy.deepcopy(BASE)


def rename_segmentation(s, new="seg"):
    old = s.perception.segmentation.name
    s.perception.segmentation.name = new
    for sc in s.scenarios.values():
        sc.semantic = new if sc.semantic == old else sc.semantic
    return new


def rename_depth(s, new="depth_x"):
    old = s.perception.depth[0].name
    s.perception.depth[0].name = new
    for sc in s.scenarios.values():
        sc.depth = new if sc.depth == old else sc.depth
    return new


def keys(s, depth_name=None, seg_name=None):
    """Every stage's key of one study: the dataset, the first depth model, the segmentation model, scenario s3's
    graphs (predicted depth and semantics), a gcn cell and an image-baseline cell of it."""
    depth_name = depth_name or s.perception.depth[0].name
    seg_name = seg_name or s.perception.segmentation.name
    sc = next(n for n, v in s.scenarios.items() if v.depth == depth_name)
    return {"dataset": dataset.dataset_key(s), "depth": predictions.model_key(s, depth_name),
            "segmentation": predictions.model_key(s, seg_name), "graphs": scenegraphs.scenario_key(s, sc),
            "cell": cell.cell_key(s, "gcn", sc, 2.0, 0), "image": cell.cell_key(s, "color_hist", "rgb", 2.0, 0)}


REFERENCE = keys(BASE)


def same_everywhere(change):
    s = study()
    extra = change(s) or {}
    assert keys(s, **extra) == REFERENCE


def new_from(stage_list, change):
    s = study()
    extra = change(s) or {}
    got = keys(s, **extra)
    changed = sorted(k for k in got if got[k] != REFERENCE[k])
    assert changed == sorted(stage_list), changed


# ---- what must not matter ------------------------------------------------------------------------------------

NOT_MATTERING = {
    "dataset.workers": lambda s: setattr(s.dataset, "workers", 7),
    "dataset.root (where the frames are)": lambda s: setattr(s.dataset, "root", "/elsewhere/dataset"),
    "perception.loader_workers": lambda s: setattr(s.perception, "loader_workers", 5),
    "scenario labels": lambda s: [setattr(v, "label", "renamed") for v in s.scenarios.values()] and None,
    "the depth model's name": lambda s: {"depth_name": rename_depth(s)},
    "the segmentation model's name": lambda s: {"seg_name": rename_segmentation(s)},
    "the depth model's role (a label)": lambda s: setattr(s.perception.depth[0], "role", "ResNeXt101"),
    "protocol.recall_k within the rankings": lambda s: setattr(s.protocol, "recall_k", [1, 2, 3]),
    "protocol.precision_k within the rankings": lambda s: setattr(s.protocol, "precision_k", [1, 10]),
    "the study's jobs": lambda s: setattr(s, "jobs", 9),
    "the cell timeout": lambda s: setattr(s, "cell_timeout", 10),
}


@pytest.mark.parametrize("what", sorted(NOT_MATTERING))
def test_a_change_that_decides_nothing_keeps_every_key(what):
    same_everywhere(NOT_MATTERING[what])


def test_a_variant_renamed_with_the_same_encoder_keeps_its_cells_key():
    s = study()
    ours = load_study("quick").variants["ours"]
    s.variants = {"ours": copy.deepcopy(ours), "mine": copy.deepcopy(ours)}
    assert cell.cell_key(s, "mine", "s1", 2.0, 0) == cell.cell_key(s, "ours", "s1", 2.0, 0)
    assert cell.cell_key(s, "ours", "s1", 2.0, 0) != cell.cell_key(s, "gcn", "s1", 2.0, 0)


# ---- what must matter ----------------------------------------------------------------------------------------

ALL = ["dataset", "depth", "segmentation", "graphs", "cell", "image"]
MATTERING = {
    "the study's seed": (ALL, lambda s: setattr(s, "seed", 5)),
    "dataset.train_settings": (ALL, lambda s: setattr(s.dataset, "train_settings", 9)),
    "the dataset's code": (ALL, lambda s: None),  # monkeypatched in the test
    "the depth model's epochs": (["depth", "graphs", "cell"], lambda s: setattr(s.perception.depth[0], "epochs", 9)),
    "perception.predict_batch": (["depth", "segmentation", "graphs", "cell"],
                                 lambda s: setattr(s.perception, "predict_batch", 3)),
    "perception.threads": (["depth", "segmentation", "graphs", "cell"], lambda s: setattr(s.perception, "threads", 1)),
    "a depth scale": (["graphs", "cell"], lambda s: setattr(s.scenarios["s3"], "depth_scale", 1.1)),
    "protocol.frames": (["graphs", "cell", "image"], lambda s: [setattr(s.protocol, "frames", 5),
                                                                setattr(s.protocol, "queries", 3)] and None),
    "gcn.val_settings": (["graphs", "cell", "image"], lambda s: setattr(s.gcn, "val_settings", 1)),
    "protocol.queries and positives (the draw)": (["cell", "image"], lambda s: [
        setattr(s.protocol, "queries", s.protocol.queries - 1),
        setattr(s.protocol, "positives", s.protocol.positives + 1)] and None),
    "a k beyond the rankings' top 10": (["cell", "image"], lambda s: setattr(s.protocol, "recall_k", [1, 20])),
    "gcn.epochs": (["cell", "image"], lambda s: setattr(s.gcn, "epochs", 7)),
    "the cells' torch threads": (["cell", "image"], lambda s: setattr(s, "threads", 3)),
}


@pytest.mark.parametrize("what", sorted(MATTERING))
def test_a_change_that_decides_a_result_gives_new_keys_from_that_stage_on(what, monkeypatch):
    stages, change = MATTERING[what]
    if what == "the dataset's code":
        real = versions.code_version

        monkeypatch.setattr(versions, "code_version", lambda stage: real(stage) + ("x" if stage == "dataset" else ""))
    new_from(stages, change)


@pytest.mark.parametrize("stage, stages", [("perception", ["depth", "segmentation", "graphs", "cell"]),
                                           ("graphs", ["graphs", "cell"]), ("cells", ["cell", "image"])])
def test_a_library_upgrade_gives_new_keys_from_its_stage_on(stage, stages, monkeypatch):
    real = versions.library_versions

    monkeypatch.setattr(versions, "library_versions",
                        lambda s: {**real(s), "torch": "9.9"} if s == stage else real(s))
    new_from(stages, lambda s: None)


def test_the_device_is_part_of_the_model_and_cell_keys(monkeypatch):
    from monolib import device

    monkeypatch.setattr(device, "device", lambda: torch.device("cuda"))
    new_from(["depth", "segmentation", "graphs", "cell", "image"], lambda s: None)


def test_a_checkpoint_by_its_content_not_its_path(tmp_path):
    first = tmp_path / "a" / "res50.pth"
    first.parent.mkdir()
    first.write_bytes(b"weights one")
    moved = tmp_path / "b" / "renamed.pth"
    moved.parent.mkdir()
    shutil.copy(first, moved)

    def with_checkpoint(path):
        s = study()
        s.perception.depth[0].checkpoint = str(path)
        return predictions.model_key(s, s.perception.depth[0].name)

    assert with_checkpoint(first) == with_checkpoint(moved) != REFERENCE["depth"]
    moved.write_bytes(b"weights two")
    assert with_checkpoint(moved) != with_checkpoint(first)


def test_the_perception_figures_are_not_part_of_its_version():
    """The stage's figures live in a module of no stage's version: an edited figure recomputes nothing. Of the
    stage's own module, a function that computes no cached output edited: the version stays; a line of the stage's
    computation edited: it moves."""
    assert not any("report.perception_figures" in modules for modules in versions.STAGE_MODULES.values())
    src = (paths.PACKAGE / "perception" / "predictions.py").read_text()
    base = versions.source_version
    drop = versions.PRESENTATION_FUNCTIONS["perception.predictions"]
    import ast

    def version(text):
        tree = ast.parse(text)
        tree.body = [n for n in tree.body if not (isinstance(n, ast.FunctionDef) and n.name in drop)]
        return base(ast.unparse(tree))

    helper = "def _write_if_changed("
    assert helper in src
    assert version(src.replace(helper, "def _write_if_changed(extra_argument=None, *, ", 1)) == version(src)
    assert version(src.replace("MAX_NONFINITE_SHARE = 0.001", "MAX_NONFINITE_SHARE = 0.01", 1)) != version(src)


@pytest.mark.slow
def test_a_new_k_is_computed_from_the_rankings_without_training(smoke_study, tmp_path):
    """A complete smoke cell, reported at other k (within its top 10): the metrics come from its rankings and the
    record is rewritten; nothing else of the cell changes."""
    from monolib.report import results

    source = paths.cell_dir("smoke", "gcn", "s1", 2.0, 0)
    folder = tmp_path / "cell"
    shutil.copytree(source, folder)
    before = {p.name: p.read_bytes() for p in folder.iterdir() if p.name != "cell.json"}
    s = study()
    s.protocol.recall_k, s.protocol.precision_k = [1, 2, 3], [1, 10]
    record = cell.refresh_metrics(folder, s)
    rankings = results.split_protocols(results.pd.read_csv(folder / "rankings.csv"))
    for name, metrics in record["metrics"].items():
        assert list(metrics) == ["recall@1", "recall@2", "recall@3", "precision@1", "precision@10"]
        assert metrics == results.recompute_metrics(rankings[name], [1, 2, 3], [1, 10])
    assert json.loads((folder / "cell.json").read_text())["metrics"] == record["metrics"]
    assert {p.name: p.read_bytes() for p in folder.iterdir() if p.name != "cell.json"} == before
    assert (record["metrics"]["paper"]["recall@1"]
            == json.loads((source / "cell.json").read_text())["metrics"]["paper"]["recall@1"])
