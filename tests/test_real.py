"""The real leg: the published graphs' development set checked and unpacked (`monolib.graphs.devset`, `make real`),
a study of folds only (``protocol.release_split: false``) run and reported over folds from another working directory,
its claims evaluated over folds, and the development set itself read as it is where ``../shared/data/`` has it."""
import lzma
import tarfile
from pathlib import Path

import pandas as pd
import pytest
import yaml

from monolib import paths
from monolib.data import folds
from monolib.data.protocols import family
from monolib.graphs import devset, published
from monolib.graphs.published import PublishedGraphError
from monolib.params import StudyError, load_study
from tests.published_files import layout, study_file, write_release

pytestmark = pytest.mark.shares_runs


DEV_ARCHIVE = paths.ROOT.parent / "shared" / "data" / "published_graphs_dev.tar.xz"
VOLUMES = [1, 2, 3, 4, 5, 6]


def dev_archive(tmp_path: Path, extra: dict[str, bytes] | None = None) -> Path:
    """A small archive in the development set's layout (``published_graphs_dev/train/*.pt`` and ``SOURCE.md``),
    with `extra` members (name inside the archive: bytes) added."""
    top = tmp_path / "src" / devset.DEV_FOLDER
    write_release(top, {"train": layout(VOLUMES, settings=1, test_volumes=[])["train"]}, cameras=1, frames=2)
    (top / "SOURCE.md").write_text("a test archive\n")
    for name, data in (extra or {}).items():
        (tmp_path / "src" / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "src" / name).write_bytes(data)
    archive = tmp_path / "dev.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        for p in sorted((tmp_path / "src").rglob("*")):
            tar.add(p, arcname=str(p.relative_to(tmp_path / "src")), recursive=False)
    return archive


def test_unpack_writes_the_files_and_refuses_a_damaged_archive(tmp_path):
    archive = dev_archive(tmp_path)
    out = tmp_path / "runs" / "published_graphs_dev"
    assert devset.unpack(archive, out) == out
    names = sorted(p.name for p in (out / "train").iterdir())
    assert names == [f"ai_{v:03d}_001_00_graphs.pt" for v in VOLUMES] and (out / "SOURCE.md").is_file()
    assert len(published.read_folder(out / "train")) == 2 * len(VOLUMES)
    before = {p.name: p.read_bytes() for p in (out / "train").iterdir()}

    cut = tmp_path / "cut.tar.xz"
    cut.write_bytes(archive.read_bytes()[: archive.stat().st_size // 2])
    with pytest.raises(PublishedGraphError, match=r"cut\.tar\.xz: not a readable \.tar\.xz archive"):
        devset.unpack(cut, out)
    with pytest.raises(PublishedGraphError, match=r"nowhere\.tar\.xz: not found"):
        devset.unpack(tmp_path / "nowhere.tar.xz", out)
    outside = dev_archive(tmp_path / "b", {"elsewhere/x.txt": b"x"})
    with pytest.raises(PublishedGraphError, match="member 'elsewhere' is outside published_graphs_dev/"):
        devset.unpack(outside, out)
    bad = dev_archive(tmp_path / "c", {f"{devset.DEV_FOLDER}/train/ai_007_001_00_graphs.pt": b"not torch"})
    with pytest.raises(PublishedGraphError, match=r"ai_007_001_00_graphs\.pt: not a readable torch file"):
        devset.unpack(bad, out)
    # nothing half-written: the folder is what the good archive wrote, and no temporary folder is left beside it
    assert {p.name: p.read_bytes() for p in (out / "train").iterdir()} == before
    assert sorted(p.name for p in out.parent.iterdir()) == ["published_graphs_dev"]
    plain = tmp_path / "xz.tar.xz"  # an xz stream that is not a tar archive
    plain.write_bytes(lzma.compress(b"hello"))
    with pytest.raises(PublishedGraphError, match="not a readable"):
        devset.unpack(plain, out)


def test_unpack_takes_a_folder_too(tmp_path):
    src = tmp_path / "mine"
    write_release(src, {"train": layout(VOLUMES, settings=1, test_volumes=[])["train"]}, cameras=1, frames=2)
    out = devset.unpack(src, tmp_path / "out")
    assert len(list((out / "train").glob("*_graphs.pt"))) == len(VOLUMES)
    with pytest.raises(PublishedGraphError, match="no train/ folder"):
        devset.unpack(src / "train", tmp_path / "out2")


def folds_only_study(tmp_path: Path, root: Path, **protocol) -> Path:
    """`study_file` as a study of folds only (3 folds, 10 frames a test setting), thresholds 0 and 1, 2 seeds, the
    undirected encoder beside `gcn`."""
    path = study_file(tmp_path, root, **{"split": "volumes", "folds": 3, "release_split": False, "frames": 10,
                                         "queries": 8, "positives": 2, **protocol})
    spec = yaml.safe_load(path.read_text())
    spec.update(name="real_test", thresholds=[0, 1], seeds=[0, 1],
                variants={"gcn_undirected": {"ablation_of": "gcn", "gcn": {"edges": "both"}}})
    spec["dataset"]["train_frames_per_setting"] = 6
    path.write_text(yaml.safe_dump(spec))
    return path


def test_release_split_false_needs_folds(tmp_path):
    with pytest.raises(StudyError, match="protocol.release_split: false .*needs protocol.split: volumes"):
        load_study(folds_only_study(tmp_path, tmp_path, split="release"))


@pytest.mark.slow
def test_a_study_of_folds_only_runs_and_reports_over_folds(tmp_path, monkeypatch):
    """A folder of training volumes alone (no test/): the release split is refused with the way out named, the folds
    run, and the report (written from another working directory) holds the tables over folds as intervals.csv,
    the edge penalty of both encoders beside the committed mini-Hypersim's, reproduces.md and the claims."""
    from monolib.io import read_json
    from monolib.report import bootstrap, claims
    from monolib.report import folds as fold_report
    from monolib.report.write import write_report
    from monolib.retrieval.grid import grid
    from monolib.study.runner import run_grid, stages

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    root = tmp_path / "graphs"
    write_release(root, {"train": layout(VOLUMES, settings=2, test_volumes=[])["train"]}, cameras=2, frames=6)
    study = load_study(folds_only_study(tmp_path, root))
    assert study.folds() == [0, 1, 2] and {c.fold for c in grid(study)} == {0, 1, 2}
    with pytest.raises(PublishedGraphError, match="test: folder not found.*release_split: false"):
        published.select(study)  # the release split of a folder without test/
    stages(study, progress=False)
    run_grid(study, progress=False, in_process=True)
    for c in grid(study):  # each fold's cell names its volumes, none on both sides
        r = read_json(paths.cell_dir(study.name, c.method, c.scenario, c.threshold, c.seed, c.fold) / "cell.json")
        assert r["fold"] == c.fold and not set(r["volumes"]["test"]) & set(r["volumes"]["train"])
    monkeypatch.chdir(tmp_path)  # the report reads the committed figures wherever it runs from
    written = write_report(study.name, study=study, n_boot=50)
    out = paths.figures_dir(study.name)
    iv = pd.read_csv(out / "intervals.csv")
    assert iv.equals(pd.read_csv(out / "folds_intervals.csv")) and set(iv["n_folds"]) == {3}
    assert "release" not in (out / "folds_table1_recall.md").read_text().split("\n")[4]
    rvs = pd.read_csv(out / "real_vs_synth.csv")
    assert set(rvs["comparison"]) == {"gcn at 1 - gcn at 0 (no edges)", "gcn_undirected at 1 - gcn_undirected at 0 "
                                      "(no edges)", "gcn_undirected at 1 - gcn at 1"}  # identical 0 m cells left out
    synth = fold_report.synth_differences(fold_report.synth_figures())
    for method in ("gcn", "gcn_undirected"):  # the mini-Hypersim side: the committed edge penalties
        got = rvs[rvs["comparison"] == f"{method} at 1 - {method} at 0 (no edges)"].iloc[0]
        want = synth[(synth["a"] == method) & (synth["b"] == method) & (synth["ta"] == 1) & (synth["k"] == 1)]
        assert got["synth"] == pytest.approx(want["diff"].iloc[0], abs=1e-4)
    assert (out / "edge_penalty.md").read_text().count("| gcn") == 2
    text = (out / "reproduces.md").read_text()
    assert "| 1 | 94.3 |" in text and "1 m against no edges: the real folds" in text
    assert {"real_vs_synth", "edge_penalty", "reproduces"} <= set(written)

    # claims over folds: the fold-level bootstrap, the tables' means
    claims_file = tmp_path / "claims.yaml"
    claims_file.write_text(yaml.safe_dump({"real_test": [
        {"id": "edges-level", "a": {"method": "gcn", "scenario": "s1", "threshold": 1},
         "b": {"method": "gcn", "scenario": "s1", "threshold": 0}, "relation": "not_above",
         "sentence": "gcn at 1 m ({a}) against no edges ({b})."}]}))
    qv = fold_report.fold_query_table(study)
    fboot = bootstrap.FoldBootstrap.for_queries(qv, 50)
    table = claims.evaluate(claims.load("real_test", claims_file), qv, iv, {"paper": fboot})
    row = iv[(iv["method"] == "gcn") & (iv["threshold"] == 1) & (iv["metric"] == "recall") & (iv["k"] == 1)].iloc[0]
    assert table["a_mean"].iloc[0] == pytest.approx(row["mean"])
    diff = bootstrap.fold_paired_difference(bootstrap.rows_of(qv, "gcn", "s1", 1.0), bootstrap.rows_of(
        qv, "gcn", "s1", 0.0), fboot, ["recall@1"]).iloc[0]
    assert (table["diff_lo"].iloc[0], table["diff_hi"].iloc[0]) == (diff["ci_lo"], diff["ci_hi"])


@pytest.mark.slow
@pytest.mark.skipif(not DEV_ARCHIVE.is_file(), reason="the development set is in ../shared/data only")
def test_the_development_set_as_it_is(tmp_path):
    """Every file of the development set parses (unpack reads each), it holds 18 volumes and no test/, the folds of
    params/real.yaml never share a volume and the same seed deals the same folds, and each fold can give the paper
    protocol its settings."""
    out = devset.unpack(DEV_ARCHIVE, tmp_path / "dev")
    assert not (out / "test").exists()
    by_split = published.read_settings(out, need_test=False)
    settings = sorted(by_split["train"])
    volumes = sorted({family(s) for s in settings})
    assert len(volumes) == 18 and len(settings) == 144 and not by_split["test"]
    real = load_study("real", check_files=False)  # its graphs_root is make real's folder; this test unpacks its own
    study = real.__class__(**{**real.__dict__, "graphs_root": str(out)})
    dealt = folds.volume_folds(volumes, study.protocol.folds, study.seed)
    assert dealt == folds.volume_folds(list(reversed(volumes)), study.protocol.folds, study.seed)
    assert sorted(v for f in dealt for v in f) == volumes
    frames = {s: len(g) for s, g in by_split["train"].items()}
    for fold in study.folds():  # the names each fold trains and tests on (what published.select reads)
        train, test, label = folds.split_names(study.at_fold(fold), settings, [])
        assert {family(s) for s in test} == set(dealt[fold]) and not {family(s) for s in train} & set(dealt[fold])
        assert sum(frames[s] >= study.protocol.frames for s in test) >= study.protocol.settings, label
        assert len(train) == study.dataset.train_settings
    split = published.select(study.at_fold(0))  # one fold read whole: the protocol's settings, no volume shared
    assert len({g.setting for g in split["test"]}) == study.protocol.settings
    assert not {family(g.setting) for g in split["test"]} & {family(g.setting) for g in split["train"] + split["val"]}


@pytest.mark.slow
def test_model_selection_on_a_study_of_folds_holds_out_volumes_of_fold_0s_training_side(tmp_path, monkeypatch):
    """`monolib bench selection` on published graphs: the inner test is as many volumes as fold 0 tests, drawn
    from its training side (never its test volumes); no image encoder is compared (no frames); each run's epochs
    are recorded, and selection.md says what was held out."""
    import math

    from monolib.graphs import scenegraphs
    from monolib.retrieval import model_selection as ms

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    root = tmp_path / "graphs"
    write_release(root, {"train": layout(VOLUMES, settings=2, test_volumes=[])["train"]}, cameras=2, frames=6)
    study = ms.split_study(load_study(folds_only_study(tmp_path, root)))
    assert study.fold == 0
    graphs = scenegraphs.load(study, ms.SCENARIO)
    tested = {family(g.setting) for g in graphs["test"]}
    families = ms.inner_families(study)
    assert families == len(tested)
    train, val, inner = ms.inner_split(graphs, families, study.seed)
    assert len({family(g.setting) for g in inner}) == families and not {family(g.setting) for g in inner} & tested
    assert not {g.setting for g in inner} & {g.setting for g in train + val}
    training = ms.Training("folds test", 1e-3, "constant", 2, (ms.GRAPH, "image_triplet"))
    df = ms.curves(study, (("gcn", 1.0), ("image_triplet", math.inf)), seeds=[0], workers=1, trainings=(training,),
                   families=families)
    assert set(df["method"]) == {"gcn"} and list(df["epoch"]) == [1, 2] and df["inner_recall@1"].between(0, 1).all()
    md = ms.markdown(ms.rules_table(df, [ms.Rule("fixed 2", "last", 1, 2, 2, training.name)]), ms.best_possible(df),
                     study.name, 1.0, families=families, volumes=True)
    assert f"{families} volumes of fold 0's training side held out as an inner test" in md
