"""The localizer's bad inputs through the real command (`monolib index`, `monolib localize`): each is one
`error:` line on stderr naming the file or option and what was expected, exit status 2, no traceback, and no
work done. The databases here are written by `localize.write_database` (the writer `monolib index` uses) from an
untrained encoder, so no study has to run; the end-to-end index + localize of the smoke study is
`tests/test_study.py::test_index_and_localize_images_it_never_saw`."""
import json

import cv2
import numpy as np
import pytest
import yaml

from monolib import cli, localize, paths
from monolib.params import load_study
from monolib.retrieval.gcn import GraphEncoder

SETTINGS = ["ai_901_001", "ai_902_001", "ai_903_001", "ai_904_001"]


@pytest.fixture
def runs(tmp_path, monkeypatch):
    """An empty runs/ and figures/: no study has run, no perception model is trained."""
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    return tmp_path / "runs"


@pytest.fixture
def image(tmp_path):
    """A real PNG query (a photo-like gradient with a box), of another size and aspect than the study's frames."""
    rgb = np.zeros((300, 500, 3), np.uint8)
    rgb[..., 0] = np.linspace(40, 220, 500)[None, :]
    rgb[..., 1] = np.linspace(200, 60, 300)[:, None]
    rgb[100:200, 150:300] = (30, 90, 160)
    path = tmp_path / "query.png"
    assert cv2.imwrite(str(path), rgb)
    return path


def study_file(tmp_path, change=None):
    """The smoke study as a file in tmp_path (same name, so its perception model tags are the smoke study's)."""
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["variants"] = {"label_embedding": {"gcn": {"label": "embedding"}}}
    if change:
        change(data)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def make_database(tmp_path, scenario="s3", method="gcn", per_setting=3):
    """A database of 4 settings x `per_setting` frames in the files `monolib index` writes."""
    study = load_study(study_file(tmp_path))
    frames = [f"{s}/cam_00/{i:04d}" for s in SETTINGS for i in range(per_setting)]
    emb = np.random.default_rng(0).normal(size=(len(frames), 64)).astype(np.float32)
    cell = {"folder": str(tmp_path / "cell"), "method": method, "scenario": scenario, "threshold": 1.0, "seed": 0,
            "metrics": {"paper": {"recall@1": 50.0}}}
    return localize.write_database(tmp_path / "db", study, cell, GraphEncoder(study.gcn_spec(method)), frames,
                                   [f.split("/")[0] for f in frames], emb)


def run(argv, capsys):
    """(exit status, the one stderr line) of `monolib ARGV`; fails unless stderr is exactly one `error:` line."""
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert "Traceback" not in captured.err and len(lines) == 1 and lines[0].startswith("error: "), captured.err
    return code, lines[0]


def test_database_files_read_back(tmp_path):
    db = make_database(tmp_path)
    meta, frames, emb = localize.read_database(db)
    assert meta["scenario"] == "s3" and meta["method"] == "gcn" and meta["study"] == "smoke"
    assert meta["study_file"] == str(tmp_path / "study.yaml") and meta["frames"] == 12
    assert frames.setting.drop_duplicates().tolist() == SETTINGS and emb.shape == (12, 64)
    np.testing.assert_array_equal(emb, np.random.default_rng(0).normal(size=(12, 64)).astype(np.float32))
    assert meta["projection"] == "monograph"  # the query graphs are built in the camera of the database's graphs


def test_a_database_keeps_its_scenarios_camera(tmp_path):
    def exact(d):
        d["scenarios"]["s3"]["projection"] = "exact"
    study = load_study(study_file(tmp_path, exact))
    cell = {"folder": str(tmp_path / "cell"), "method": "gcn", "scenario": "s3", "threshold": 1.0, "seed": 0,
            "metrics": {"paper": {"recall@1": 50.0}}}
    db = localize.write_database(tmp_path / "db", study, cell, GraphEncoder(study.gcn_spec("gcn")), ["a"], ["s"],
                                 np.zeros((1, 64), np.float32))
    assert localize.read_database(db)[0]["projection"] == "exact"


def test_no_database_folder(tmp_path, runs, image, capsys):
    code, line = run(["localize", image, "--db", tmp_path / "nope"], capsys)
    assert code == 2
    assert line == (f"error: {tmp_path / 'nope'}: no database folder; build the database with "
                    f"`monolib index STUDY --out {tmp_path / 'nope'}`")


def test_a_database_file_missing(tmp_path, runs, image, capsys):
    db = make_database(tmp_path)
    (db / "frames.csv").unlink()
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2 and line.startswith(f"error: {db / 'frames.csv'}: missing; build the database with"), line


def test_index_before_the_study_has_run(tmp_path, runs, capsys):
    code, line = run(["index", "smoke", "--out", tmp_path / "db"], capsys)
    assert code == 2
    assert line.startswith(f"error: {runs / 'smoke' / 'cells'}: no finished graph-method cell with predicted depth "
                           "and semantics and a saved model.pt; run `monolib study smoke` first"), line
    assert not (tmp_path / "db").exists()


def test_index_with_an_unknown_method(tmp_path, runs, capsys):
    code, line = run(["index", study_file(tmp_path), "--method", "nope", "--out", tmp_path / "db"], capsys)
    assert code == 2
    assert line == (f"error: {tmp_path / 'study.yaml'}: --method nope: not a method of study smoke; "
                    "expected one of gcn, label_embedding")
    # an image baseline is a method of the project, but not of this study: its cells are not there to encode with
    code, line = run(["index", "smoke", "--method", "color_hist", "--out", tmp_path / "db"], capsys)
    assert code == 2 and "--method color_hist: not a method of study smoke; expected one of gcn" in line
    assert not (tmp_path / "db").exists()


def test_a_scenario_removed_from_the_study_file(tmp_path, runs, image, capsys):
    db = make_database(tmp_path, scenario="s3")
    study_file(tmp_path, lambda d: d["scenarios"].pop("s3"))
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2
    assert line == (f"error: {db / 'meta.json'}: scenario 's3' is not in the study file {tmp_path / 'study.yaml'} "
                    f"(its scenarios: s1, s2, s4); rebuild the database with `monolib index smoke --out {db}`")


def test_a_method_removed_from_the_study_file(tmp_path, runs, image, capsys):
    db = make_database(tmp_path, method="label_embedding")
    study_file(tmp_path, lambda d: d.pop("variants"))
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2
    assert line.startswith(f"error: {db / 'meta.json'}: method 'label_embedding' is not a graph method of the study "
                           f"file {tmp_path / 'study.yaml'} (its graph methods: gcn)"), line


@pytest.mark.parametrize("k, message", [
    (0, "--k 0: expected at least 1 (the number of nearest settings to list)"),
    (-3, "--k -3: expected at least 1 (the number of nearest settings to list)"),
    (5, "--k 5: the database {db} holds 4 settings; expected 1 to 4"),
    (50, "--k 50: the database {db} holds 4 settings; expected 1 to 4"),
])
def test_k_outside_one_to_the_number_of_settings(tmp_path, runs, image, capsys, k, message):
    db = make_database(tmp_path)  # 4 settings of 3 frames: 12 frames, so k is counted in settings, not frames
    code, line = run(["localize", image, "--db", db, "--k", k], capsys)
    assert code == 2 and line == "error: " + message.format(db=db)


@pytest.mark.parametrize("k", [[], ["--k", 4], ["--k", 1]])
def test_k_up_to_the_number_of_settings_passes_the_check(tmp_path, runs, image, capsys, k):
    """k = 1 and k = 4 of 4 settings are accepted, and so is no --k (5 by default: all 4 of this database); what
    stops this database next is its untrained perception model, also one clear error (nothing under this runs/)."""
    db = make_database(tmp_path)
    code, line = run(["localize", image, "--db", db, *k], capsys)
    assert code == 2 and "--k" not in line
    assert f"{runs / 'smoke' / 'models'}" in line and "model 'deeplab' is not trained" in line, line


def test_a_database_that_is_not_a_database(tmp_path, runs, image, capsys):
    db = make_database(tmp_path)
    meta = json.loads((db / "meta.json").read_text())
    del meta["scenario"]
    (db / "meta.json").write_text(json.dumps(meta))
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2 and line.startswith(f"error: {db / 'meta.json'}: no key 'scenario'; expected the keys"), line
    make_database(tmp_path)
    np.save(db / "embeddings.npy", np.zeros((5, 64), np.float32))  # 12 frames, 5 embeddings
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2 and "(shape [5, 64]) disagree; expected columns frame, setting and one embedding" in line, line


# ---- image-method databases ---------------------------------------------------------------------------------------

def image_database(tmp_path, method="imagenet_gem", change=None):
    """A database of an image method (its descriptor of 4 settings' made-up frames), the way `monolib index
    --method` writes one."""
    from monolib.retrieval import pretrained

    def with_method(d):
        d["methods"] = ["gcn", method]
        if change:
            change(d)
    study = load_study(study_file(tmp_path, with_method))
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (8, 96, 128, 3), dtype=np.uint8)
    emb = pretrained.describer(method, {})(rgb)
    frames = [f"{s}/cam_00/{i:04d}" for s in SETTINGS for i in range(2)]
    cell = {"folder": str(tmp_path / "cell"), "method": method, "scenario": "rgb", "threshold": "inf", "seed": 0,
            "metrics": {"paper": {"recall@1": 50.0}}}
    db = localize.write_database(tmp_path / "db", study, cell, {}, frames, [f.split("/")[0] for f in frames], emb)
    return db, rgb


def test_an_image_database_localizes_with_its_descriptor_alone(tmp_path, runs):
    """No perception model exists (empty runs/): an image method's database needs none. A query that is one of the
    database's images finds its setting first, at distance 0."""
    db, rgb = image_database(tmp_path)
    meta, _, emb = localize.read_database(db)
    assert meta["kind"] == "image" and meta["models"] == {} and meta["projection"] is None
    assert emb.shape == (8, 1280)
    path = tmp_path / "q.png"
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb[5], cv2.COLOR_RGB2BGR))
    (result,) = localize.localize([str(path)], db, k=2)
    assert result["matches"][0]["setting"] == SETTINGS[2] and result["matches"][0]["distance"] < 1e-3


def test_an_image_method_removed_from_the_study_file(tmp_path, runs, image, capsys):
    db, _ = image_database(tmp_path)
    study_file(tmp_path)  # the smoke study's methods: gcn only
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2
    assert line == (f"error: {db / 'meta.json'}: image method 'imagenet_gem' is not a method of the study file "
                    f"{tmp_path / 'study.yaml'} (its methods: gcn); rebuild the database with "
                    f"`monolib index smoke --out {db}`")


def test_index_of_an_image_method_before_its_cells(tmp_path, runs, capsys):
    path = study_file(tmp_path, lambda d: d.update(methods=["gcn", "imagenet_vlad"]))
    code, line = run(["index", path, "--method", "imagenet_vlad", "--out", tmp_path / "db"], capsys)
    assert code == 2
    assert line == (f"error: {runs / 'smoke' / 'cells'}: no finished imagenet_vlad cell with a saved model.pt; run "
                    f"`monolib study smoke` first")
