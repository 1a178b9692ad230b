"""Folds by volume and the subsample of training settings on published graph files written here in the release's
format (the release is not in this repository), and the single released sample file read as it is."""

import numpy as np
import pandas as pd
import pytest
import yaml

from monolib import paths, versions
from monolib.data import folds
from monolib.data.protocols import family
from monolib.graphs import published
from monolib.graphs.published import PublishedGraphError
from monolib.params import StudyError, load_study
from monolib.retrieval.grid import grid
from tests.published_files import layout, study_file, write_release

pytestmark = pytest.mark.shares_runs


SAMPLE = paths.ROOT.parent / "shared" / "data" / "published_graphs_sample" / "ai_001_001_00_graphs.pt"
VOLUMES = [1, 2, 3, 4, 5, 6]


@pytest.fixture
def release(tmp_path):
    root = tmp_path / "graphs"
    write_release(root, layout(VOLUMES, settings=2, test_volumes=[5, 6]), cameras=2, frames=2)
    return root


@pytest.mark.skipif(not SAMPLE.is_file(), reason="the released sample file is in ../shared/data only")
def test_the_released_sample_file_reads_as_it_is():
    graphs = published.read_file(SAMPLE)
    assert graphs and {g.setting for g in graphs} == {"ai_001_001"}
    assert all(g.frame.startswith("ai_001_001/cam_00/") for g in graphs)
    assert all(g.x.shape[1] == 4 and g.pair_index.shape[1] == g.pair_len.shape[0] for g in graphs)
    assert all(bool((g.pair_index[0] < g.pair_index[1]).all()) for g in graphs)  # the release's i < j, kept


def test_folds_never_share_a_volume_and_the_seed_decides():
    vols = [f"ai_{v:03d}" for v in range(1, 27)]
    dealt = folds.volume_folds(vols, 5, seed=0)
    assert sorted(v for f in dealt for v in f) == vols  # every volume in exactly one fold
    assert max(map(len, dealt)) - min(map(len, dealt)) <= 1
    assert folds.volume_folds(list(reversed(vols)), 5, seed=0) == dealt  # the order of the names does not matter
    assert folds.volume_folds(vols, 5, seed=1) != dealt
    with pytest.raises(StudyError, match="protocol.folds: 5 folds asked, the data holds 3 volumes"):
        folds.volume_folds(vols[:3], 5, seed=0)


def test_each_fold_tests_on_its_volumes_and_trains_on_the_others(tmp_path, release):
    study = load_study(study_file(tmp_path, release, split="volumes", folds=3))
    assert [c.fold for c in grid(study)] == [None, None, 0, 0, 1, 1, 2, 2]
    tested = []
    for fold in range(3):
        split = published.select(study.at_fold(fold))
        test_vols = {family(g.setting) for g in split["test"]}
        train_vols = {family(g.setting) for g in split["train"] + split["val"]}
        assert test_vols and not test_vols & train_vols
        assert test_vols <= set(folds.volume_folds([f"ai_{v:03d}" for v in VOLUMES], 3, 0)[fold])
        tested += sorted(test_vols)
    assert len(tested) == len(set(tested))  # no volume tested twice
    with pytest.raises(StudyError, match="fold 3"):
        study.at_fold(3)


def test_a_fold_with_too_few_test_settings_is_one_error_naming_the_fold(tmp_path, release):
    study = load_study(study_file(tmp_path, release, split="volumes", folds=6, settings=3))
    with pytest.raises(PublishedGraphError, match=r"fold 0 of 6 \(test volumes ai_0\d\d\).*needs 3 test settings"):
        published.select(study.at_fold(0))


def test_train_settings_is_a_seeded_subsample(tmp_path, release):
    path = study_file(tmp_path, release)
    spec = yaml.safe_load(path.read_text())
    spec["dataset"]["train_settings"] = 3
    path.write_text(yaml.safe_dump(spec))
    study = load_study(path)
    names = lambda s: sorted({g.setting for k in ("train", "val") for g in published.select(s)[k]})  # noqa: E731
    picked = names(study)
    assert len(picked) == 3 and picked == names(load_study(path))
    assert len(names(load_study(study_file(tmp_path, release)))) == 8  # default: every training setting
    spec["dataset"]["train_settings"] = 2
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(StudyError, match="dataset.train_settings: .*more than gcn.val_settings"):
        load_study(path)


@pytest.mark.parametrize("key, value, words", [
    ("split", "random", "protocol.split: expected one of release, volumes"),
    ("folds", 1, "protocol.folds: expected at least 2"),
])
def test_bad_fold_keys_name_the_key(tmp_path, release, key, value, words):
    with pytest.raises(StudyError, match=words):
        load_study(study_file(tmp_path, release, **{key: value}))


def test_the_mini_hypersim_refuses_folds_and_keeps_its_keys(monkeypatch):
    """Studies without folds keep their cell names, their data and graph keys (computed with the code before folds
    existed, the code and library versions, which change with any edit, held fixed) and a cell key without a fold
    part."""
    from monolib.data import dataset
    from monolib.graphs import scenegraphs
    from monolib.retrieval import cell

    monkeypatch.setattr(versions, "code_version", lambda stage: "CODE")
    monkeypatch.setattr(versions, "library_versions", lambda stage: "LIBS")
    expected = {"smoke": ("e3d6383b8605", "fd0faac3849e"), "quick": ("3fca786354f6", "4da1e7b07a49")}
    for name, keys in expected.items():
        s = load_study(name, check_files=False)
        assert s.folds() == [None] and {c.fold for c in grid(s)} == {None}
        exact_key = dataset.dataset_key(s)
        s.dataset.coplanar = "embree"  # the renderer of the code these keys were computed with
        dk = dataset.dataset_key(s)
        assert exact_key != dk  # the renderer is in the key: a cache of the other one is not handed back
        got = (dk, scenegraphs.scenario_key(s, "s1", dk, {m: "M" for m in s.model_names()}))
        assert got == keys
        assert s.fold_key() == {}
        assert cell.cell_key(s, "gcn", "s1", 1.0, 0, inputs="I") == cell.cell_key(s.at_fold(None), "gcn", "s1", 1.0,
                                                                                 0, inputs="I")
        assert cell.cell_folder(s, "gcn", "s1", 1.0, 0) == paths.RUNS / name / "cells" / "gcn" / "s1__t1__s0"
    from monolib.params import SYNTH_TRAIN_SETTINGS, DatasetSpec
    assert (DatasetSpec().train_settings == SYNTH_TRAIN_SETTINGS
            and DatasetSpec(source="hypersim").train_settings is None)
    s = load_study("smoke", check_files=False)
    s.protocol.split = "volumes"
    from monolib.params import _check
    with pytest.raises(StudyError, match="protocol.split: folds by volume need real volumes"):
        _check(s, check_files=False)


def test_a_killed_fold_resumes_and_the_cells_record_their_fold(tmp_path, release, monkeypatch):
    """The grid of a study with folds run in this process; a fold's cells lost as a killed run loses them (no
    cell.json) run again, the other folds' are kept; the fold assignment can be read back from the cells."""
    from monolib.io import read_json
    from monolib.study.runner import run_grid, stages

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    study = load_study(study_file(tmp_path, release, split="volumes", folds=3))
    study.thresholds = [1.0]
    stages(study, progress=False)
    first = run_grid(study, progress=False, in_process=True)
    assert first["ran"] == 4  # the release split and 3 folds
    cells = {c.fold: paths.cell_dir(study.name, c.method, c.scenario, c.threshold, c.seed, c.fold) for c in grid(study)}
    assert sorted(p.name for p in cells.values()) == ["s1__t1__s0", "s1__t1__s0__f0", "s1__t1__s0__f1",
                                                      "s1__t1__s0__f2"]
    records = {f: read_json(cells[f] / "cell.json") for f in (0, 1, 2)}
    assert {f: r["fold"] for f, r in records.items()} == {0: 0, 1: 1, 2: 2}
    for r in records.values():  # the fold assignment read from the cells: no volume on both sides
        assert (r["volumes"]["test"] and r["volumes"]["train"]
                and not set(r["volumes"]["test"]) & set(r["volumes"]["train"]))
    assert "fold" not in read_json(cells[None] / "cell.json")
    tested = [{family(s) for s in r["protocols"]["paper"]["settings"]} for r in records.values()]
    assert not tested[0] & tested[1] and not tested[1] & tested[2] and not tested[0] & tested[2]
    (cells[1] / "cell.json").unlink()  # killed while fold 1 ran: its other files stay, its record was never written
    again = run_grid(study, progress=False, in_process=True)
    assert again["ran"] == 1 and set(again["cell_seconds"]) == {grid(study)[2].name}
    assert read_json(cells[0] / "cell.json")["key"] == records[0]["key"]


def test_the_report_over_folds(tmp_path, release, monkeypatch):
    """Tables over folds with the release column, folds.md with each fold's test volumes, and real_vs_synth.md
    beside the committed quick figures, from a small grid of the files written here (2 seeds, thresholds 0 and 1,
    a variant)."""
    from monolib.report import folds as fold_report
    from monolib.report.write import write_report
    from monolib.study.runner import run_grid, stages

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    root = tmp_path / "graphs12"  # 12 frames a setting: the fidelity statistics take settings of >= 10 frames
    write_release(root, layout(VOLUMES, settings=2, test_volumes=[5, 6]), cameras=2, frames=6)
    path = study_file(tmp_path, root, split="volumes", folds=3, frames=10, queries=8, positives=2)
    spec = yaml.safe_load(path.read_text())
    spec.update(thresholds=[0, 1], seeds=[0, 1], variants={"ours": {"gcn": {"pooling": "meanmax"}, "thresholds": [0]}})
    path.write_text(yaml.safe_dump(spec))
    study = load_study(path)
    stages(study, progress=False)
    run_grid(study, progress=False, in_process=True)
    written = write_report(study.name, study=study, n_boot=50)
    out = paths.figures_dir(study.name)
    assert out == tmp_path / "runs" / study.name / "figures"
    t1 = pd.read_csv(out / "folds_table1_recall.csv")
    assert set(t1["n_folds"]) == {3} and set(t1["n_seeds"]) == {2}
    assert (t1["release"].notna().all() and (t1["folds_lo"] <= t1["folds"]).all()
            and (t1["folds"] <= t1["folds_hi"]).all())
    fid = pd.read_csv(out / "folds.csv")
    assert list(fid["split"]) == ["release", "fold 0", "fold 1", "fold 2"]
    assert (fid["test settings"] == 2).all() and fid["nodes / graph"].between(2, 9).all()
    assert fid["Jaccard within"].between(0, 1).all()
    vols = [set(v.split(", ")) for v in fid["test volumes"][1:]]
    assert not (vols[0] & vols[1] or vols[1] & vols[2] or vols[0] & vols[2])
    rvs = pd.read_csv(out / "real_vs_synth.csv")
    assert set(rvs["comparison"]) == {"gcn at 1 - gcn at 0 (no edges)", "ours at 0 (no edges) - gcn at 0 (no edges)"}
    quick = fold_report.synth_differences(fold_report.synth_figures())
    got = rvs[(rvs["comparison"].str.startswith("gcn at 1")) & (rvs["metric"] == "recall@1")].iloc[0]
    want = quick[(quick["a"] == "gcn") & (quick["b"] == "gcn") & (quick["ta"] == 1) & (quick["metric"] == "recall")
                 & (quick["k"] == 1)].iloc[0]
    assert got["synth"] == pytest.approx(want["diff"], abs=1e-4)
    assert "real_vs_synth" in written and (out / "folds.md").read_text().startswith("# The folds of")


def test_the_fold_bootstrap_resamples_folds():
    """Folds of different means: the interval over folds is wider than within the folds alone, and a group against
    itself differs by exactly 0."""
    from monolib.report import bootstrap

    rows = [(f, s, f"ai_{f:03d}_{n:03d}", q, 100.0 * (f == 0) + (q % 2)) for f in range(4) for s in (0, 1)
            for n in range(3) for q in range(5)]
    qv = pd.DataFrame(rows, columns=["fold", "seed", "setting", "query", "recall@1"]).assign(
        method="gcn", scenario="s1", threshold=1.0, protocol="paper")
    fboot = bootstrap.FoldBootstrap.for_queries(qv, n_boot=200)
    iv = bootstrap.fold_intervals(qv, fboot).iloc[0]
    assert iv["mean"] == pytest.approx(np.mean([100.4, 0.4, 0.4, 0.4]))
    assert iv["ci_lo"] < 10 and iv["ci_hi"] > 40  # one fold of four at 100: the fold draw decides
    same = bootstrap.fold_paired_difference(qv, qv, fboot).iloc[0]
    assert same["diff"] == 0 and same["ci_lo"] == 0 and same["ci_hi"] == 0 and not same["significant"]


def test_folds_refuse_what_would_train_on_a_test_volume(tmp_path, release):
    """Perception models and image encoders train on the release's training split, which holds other folds' test
    volumes: a study with folds by volume runs ground-truth graph scenarios only."""
    path = study_file(tmp_path, release, split="volumes")
    spec = yaml.safe_load(path.read_text())
    spec["dataset"] = {"source": "hypersim", "root": str(tmp_path)}
    spec.pop("graphs_root")
    path.write_text(yaml.safe_dump({**spec, "scenarios": {"s2": {"depth": "depth_r18", "semantic": "gt"}}}))
    with pytest.raises(StudyError, match="scenarios.s2: protocol.split: volumes needs ground-truth scenarios"):
        load_study(path)
    path.write_text(yaml.safe_dump({**spec, "methods": ["gcn", "color_hist"]}))
    with pytest.raises(StudyError, match="methods: protocol.split: volumes runs graph methods only"):
        load_study(path)


class _Download:
    """What frame selection reads of a Hypersim download (`HypersimDataset`): settings per split, frames per
    setting (6 volumes of 2 settings, 5 frames each; volumes 5 and 6 in the test split, volume 4 in val)."""
    root = "download"

    def settings(self, split=None):
        split_of = {5: "test", 6: "test", 4: "val"}
        return [f"ai_{v:03d}_{n:03d}" for v in VOLUMES for n in (1, 2)
                if split is None or split_of.get(v, "train") == split]

    def frames(self, setting):
        from types import SimpleNamespace
        return [SimpleNamespace(setting=setting, key=f"{setting}/cam_00/{i:04d}") for i in range(5)]


def test_folds_of_a_hypersim_download(tmp_path, release):
    """The same folds on a real download's frame selection (`dataset.source: hypersim`): the release split is the
    download's, each fold tests on its volumes and trains on the others, the subsample keeps `train_settings`."""
    from monolib.data.selection import select_frames

    path = study_file(tmp_path, release, split="volumes", folds=3, frames=5, queries=4, positives=1)
    spec = yaml.safe_load(path.read_text())
    spec.pop("graphs_root")
    spec["dataset"] = {"source": "hypersim", "root": str(tmp_path), "train_settings": 5,
                       "train_frames_per_setting": 2}
    path.write_text(yaml.safe_dump(spec))
    study, ds = load_study(path), _Download()
    release_sel = select_frames(study, ds, 2)
    assert {family(f.setting) for f in release_sel.test} == {"ai_005", "ai_006"}
    for fold in range(3):
        sel = select_frames(study.at_fold(fold), ds, 2)
        test, train = {family(f.setting) for f in sel.test}, {family(f.setting) for f in sel.train + sel.val}
        assert test and train and not test & train
        assert len({f.setting for f in sel.train + sel.val}) == 5
