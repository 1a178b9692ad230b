"""The localizer's bad inputs through the real command (`monolib index`, `monolib localize`): each is one
`error:` line on stderr naming the file or option and what was expected, exit status 2, no traceback, and no
work done; and how a photo is read (`localize.read_image`), each case a real file. The databases here are written
by `localize.write_database` (the writer `monolib index` uses) from an untrained encoder and untrained perception
networks of the smoke study's specs, so no study has to run; the end-to-end index + localize of the smoke study is
`tests/test_study.py::test_index_and_localize_images_it_never_saw` and `tests/test_localize_places.py`."""
import copy
import json
import resource
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch
import yaml

from PIL import Image

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


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """Untrained segmentation and depth networks of the smoke study's specs, saved as the perception stage saves
    them: ``{role: (model name, file)}`` for `localize.write_database`."""
    from monolib.perception import depth, predictions, segmentation

    s = load_study("smoke")
    folder = tmp_path_factory.mktemp("weights")
    out = {}
    for role, name in (("semantic", "deeplab"), ("depth", "depth_a")):
        spec, task = predictions._spec(s, name)
        spec = copy.copy(spec)
        spec.pretrained = False
        net = segmentation if task == "segmentation" else depth
        torch.manual_seed(0)  # the same untrained weights each session
        net.save_model(net.build_model(spec), folder / f"{name}.pt")
        out[role] = (name, folder / f"{name}.pt")
    return out


def study_file(tmp_path, change=None):
    """The smoke study as a file in tmp_path (same name, so its perception model tags are the smoke study's)."""
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["variants"] = {"label_embedding": {"gcn": {"label_encoding": "embedding"}}}
    if change:
        change(data)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def make_database(tmp_path, weights, scenario="s3", method="gcn", per_setting=3):
    """A database of 4 settings x `per_setting` frames in the files `monolib index` writes."""
    study = load_study(study_file(tmp_path))
    frames = [f"{s}/cam_00/{i:04d}" for s in SETTINGS for i in range(per_setting)]
    emb = np.random.default_rng(0).normal(size=(len(frames), 64)).astype(np.float32)
    cell = {"folder": str(tmp_path / "cell"), "method": method, "scenario": scenario, "threshold": 1.0, "seed": 0,
            "metrics": {"paper": {"recall@1": 50.0}}}
    return localize.write_database(tmp_path / "db", study, cell, GraphEncoder(study.gcn_spec(method)), frames,
                                   [f.split("/")[0] for f in frames], emb, perception_files=weights)


def run(argv, capsys):
    """(exit status, the one stderr line) of `monolib ARGV`; fails unless stderr is exactly one `error:` line."""
    code = cli.main([str(a) for a in argv])
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line.strip()]
    assert "Traceback" not in captured.err and len(lines) == 1 and lines[0].startswith("error: "), captured.err
    return code, lines[0]


def test_database_files_read_back(tmp_path, weights):
    db = make_database(tmp_path, weights)
    meta, frames, emb = localize.read_database(db)
    assert meta["scenario"] == "s3" and meta["method"] == "gcn" and meta["study"] == "smoke"
    assert meta["study_file"] == str(tmp_path / "study.yaml") and meta["frames"] == 12
    assert frames.setting.drop_duplicates().tolist() == SETTINGS and emb.shape == (12, 64)
    np.testing.assert_array_equal(emb, np.random.default_rng(0).normal(size=(12, 64)).astype(np.float32))
    assert meta["projection"] == "monograph"  # the query graphs are built in the camera of the database's graphs


def test_a_database_keeps_its_scenarios_camera(tmp_path, weights):
    def exact(d):
        d["scenarios"]["s3"]["projection"] = "exact"
    study = load_study(study_file(tmp_path, exact))
    cell = {"folder": str(tmp_path / "cell"), "method": "gcn", "scenario": "s3", "threshold": 1.0, "seed": 0,
            "metrics": {"paper": {"recall@1": 50.0}}}
    db = localize.write_database(tmp_path / "db", study, cell, GraphEncoder(study.gcn_spec("gcn")), ["a"], ["s"],
                                 np.zeros((1, 64), np.float32), perception_files=weights)
    assert localize.read_database(db)[0]["projection"] == "exact"


def test_no_database_folder(tmp_path, runs, image, capsys):
    code, line = run(["localize", image, "--db", tmp_path / "nope"], capsys)
    assert code == 2
    assert line == (f"error: {tmp_path / 'nope'}: no database folder; build the database with "
                    f"`monolib index STUDY --out {tmp_path / 'nope'}`")


def test_a_database_file_missing(tmp_path, runs, image, capsys, weights):
    db = make_database(tmp_path, weights)
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


def test_a_database_does_not_read_its_study_file(tmp_path, runs, image, capsys, weights):
    """A database holds its models: its study file changed (the scenario and the method gone) or removed, with
    an empty runs/, it still answers."""
    db = make_database(tmp_path, weights, method="label_embedding")
    study_file(tmp_path, lambda d: (d["scenarios"].pop("s3"), d.pop("variants")))
    assert cli.main(["localize", str(image), "--db", str(db), "--k", "2", "--json"]) == 0
    assert [m["rank"] for m in json.loads(capsys.readouterr().out)[0]["matches"]] == [1, 2]
    (tmp_path / "study.yaml").unlink()
    assert cli.main(["localize", str(image), "--db", str(db), "--k", "1"]) == 0


def test_a_database_of_other_models_or_code_is_refused(tmp_path, runs, image, capsys, weights):
    db = make_database(tmp_path, weights)
    meta = json.loads((db / "meta.json").read_text())
    (db / "depth.pt").write_bytes((db / "depth.pt").read_bytes()[:-1] + b"x")  # another model's file
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2 and line.startswith(f"error: {db / 'depth.pt'}: sha256 "), line
    assert "the depth state: the database was made by other models than those it holds" in line, line
    make_database(tmp_path, weights)
    meta = json.loads((db / "meta.json").read_text())
    (db / "meta.json").write_text(json.dumps({**meta, "code": {**meta["code"], "graphs": "000000000000"}}))
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2 and line.startswith(f"error: {db / 'meta.json'}: made by other code: its graphs code version "
                                         "000000000000, this installation's "), line
    (db / "meta.json").write_text(json.dumps({**meta, "format": 1}))
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2 and "a database of format 1; this installation reads format 2; rebuild it with" in line, line


@pytest.mark.parametrize("k, message", [
    (0, "--k 0: expected at least 1 (the number of nearest places to list)"),
    (-3, "--k -3: expected at least 1 (the number of nearest places to list)"),
    (5, "--k 5: the database {db} holds 4 places; expected 1 to 4"),
    (50, "--k 50: the database {db} holds 4 places; expected 1 to 4"),
])
def test_k_outside_one_to_the_number_of_places(tmp_path, runs, image, capsys, k, message, weights):
    db = make_database(tmp_path, weights)  # 4 settings of 3 frames: 12 frames, so k is counted in settings, not frames
    code, line = run(["localize", image, "--db", db, "--k", k], capsys)
    assert code == 2 and line == "error: " + message.format(db=db)


@pytest.mark.parametrize("k, n", [([], 4), (["--k", 4], 4), (["--k", 1], 1)])
def test_k_up_to_the_number_of_places(tmp_path, runs, image, capsys, weights, k, n):
    """k = 1 and k = 4 of 4 places are answered, and so is no --k (5 by default: all 4 of this database), with
    an empty runs/ (the database holds its networks)."""
    db = make_database(tmp_path, weights)
    assert cli.main(["localize", str(image), "--db", str(db), "--json", *map(str, k)]) == 0
    matches = json.loads(capsys.readouterr().out)[0]["matches"]
    assert [m["rank"] for m in matches] == list(range(1, n + 1)) and len({m["place"] for m in matches}) == n


def test_a_database_that_is_not_a_database(tmp_path, runs, image, capsys, weights):
    db = make_database(tmp_path, weights)
    meta = json.loads((db / "meta.json").read_text())
    del meta["scenario"]
    (db / "meta.json").write_text(json.dumps(meta))
    code, line = run(["localize", image, "--db", db], capsys)
    assert code == 2 and line.startswith(f"error: {db / 'meta.json'}: no key 'scenario'; expected the keys"), line
    make_database(tmp_path, weights)
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
    assert result["matches"][0]["place"] == SETTINGS[2] and result["matches"][0]["distance"] < 1e-3


def test_an_image_database_does_not_read_its_study_file(tmp_path, runs, image, capsys):
    db, _ = image_database(tmp_path)
    study_file(tmp_path)  # the smoke study's methods: gcn only
    assert cli.main(["localize", str(image), "--db", str(db), "--k", "1"]) == 0


def test_index_of_an_image_method_before_its_cells(tmp_path, runs, capsys):
    path = study_file(tmp_path, lambda d: d.update(methods=["gcn", "imagenet_vlad"]))
    code, line = run(["index", path, "--method", "imagenet_vlad", "--out", tmp_path / "db"], capsys)
    assert code == 2
    assert line == (f"error: {runs / 'smoke' / 'cells'}: no finished imagenet_vlad cell with a saved model.pt; run "
                    f"`monolib study smoke` first")


# ---- photos as a photo viewer shows them (real files, `localize.read_image`) ------------------------------------

def gradient(h=90, w=120):
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = np.linspace(0, 255, w)[None, :]
    rgb[..., 1] = np.linspace(255, 0, h)[:, None]
    rgb[..., 2] = 77
    return rgb


def test_grayscale_rgba_and_16_bit_images_read_as_rgb(tmp_path):
    rgb = gradient()
    gray = rgb[..., 0]
    Image.fromarray(gray).save(tmp_path / "gray.png")
    Image.fromarray(gray).save(tmp_path / "gray.jpg", quality=95)
    rgba = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], axis=2)
    rgba[:, :60, 3] = 0  # the left half transparent
    Image.fromarray(rgba).save(tmp_path / "rgba.png")
    cv2.imwrite(str(tmp_path / "rgb16.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR).astype(np.uint16) * 257)
    cv2.imwrite(str(tmp_path / "gray16.png"), gray.astype(np.uint16) * 257)
    for name, expected in (("gray.png", np.repeat(gray[..., None], 3, 2)), ("rgb16.png", rgb),
                           ("gray16.png", np.repeat(gray[..., None], 3, 2))):
        out = localize.read_image(tmp_path / name)
        assert out.dtype == np.uint8 and out.shape == (90, 120, 3), name
        np.testing.assert_array_equal(out, expected, err_msg=name)
    out = localize.read_image(tmp_path / "gray.jpg")
    assert out.shape == (90, 120, 3) and np.abs(out[..., 0].astype(int) - gray).max() <= 8
    out = localize.read_image(tmp_path / "rgba.png")
    assert (out[:, :60] == 255).all()  # transparent: composited over white
    np.testing.assert_array_equal(out[:, 60:], rgb[:, 60:])


def test_an_exif_rotated_jpeg_is_turned_upright(tmp_path):
    """A camera held upright stores a landscape buffer with EXIF orientation 6 (rotate 90 degrees clockwise to
    view): the image read is portrait, its top the buffer's left side."""
    rgb = gradient(90, 120)
    exif = Image.Exif()
    exif[0x0112] = 6
    Image.fromarray(rgb).save(tmp_path / "rotated.jpg", quality=95, exif=exif)
    out = localize.read_image(tmp_path / "rotated.jpg")
    assert out.shape == (120, 90, 3)
    upright = np.rot90(rgb, k=-1)
    assert np.abs(out.astype(int) - upright).mean() < 3


def test_a_huge_jpeg_decodes_reduced_in_bounded_memory(tmp_path):
    """A 12,000 x 9,000 JPEG (324 MB as full-size RGB) read for a 256 x 192 study: decoded at 1/8 scale; the
    process's peak memory grows by far less than the full image."""
    path = tmp_path / "huge.jpg"
    big = np.zeros((9000, 12000, 3), np.uint8)
    big[..., 1] = 120
    big[::500] = 255
    Image.fromarray(big).save(path, quality=80)
    del big
    code = (f"import resource; from monolib import localize; before = resource.getrusage(resource.RUSAGE_SELF)."
            f"ru_maxrss; out = localize.read_image({str(path)!r}, 512); after = resource.getrusage("
            f"resource.RUSAGE_SELF).ru_maxrss; print(out.shape[0], out.shape[1], (after - before) // 1024)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    h, w, grown_mb = map(int, out.stdout.split())
    assert (h, w) == (1125, 1500)
    assert grown_mb < 100, grown_mb
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss > 0


def test_unreadable_and_other_formats_are_one_clear_error(tmp_path):
    (tmp_path / "broken.jpg").write_bytes(b"\xff\xd8\xff not really a jpeg")
    Image.fromarray(gradient()).save(tmp_path / "image.gif")
    (tmp_path / "folder.png").mkdir()
    with pytest.raises(localize.LocalizeError, match=r"broken.jpg: not a readable image \(expected PNG or JPEG"):
        localize.read_image(tmp_path / "broken.jpg")
    with pytest.raises(localize.LocalizeError, match=r"image.gif: a GIF image; expected PNG or JPEG"):
        localize.read_image(tmp_path / "image.gif")
    for missing in ("nope.png", "folder.png"):
        with pytest.raises(localize.LocalizeError, match=rf"{missing}: image file not found"):
            localize.read_image(tmp_path / missing)


# ---- places folders ---------------------------------------------------------------------------------------------

def test_a_places_folder_skips_and_lists_what_is_not_an_image(tmp_path):
    root = tmp_path / "places"
    for place, files in (("kitchen", ["a.JPG", "b.jpeg", "notes.txt"]), ("office", ["c.Png"])):
        (root / place).mkdir(parents=True)
        for f in files:
            (root / place / f).write_bytes(b"x")
    (root / "kitchen" / "older").mkdir()
    (root / "kitchen" / ".DS_Store").write_bytes(b"x")
    (root / "loose.jpg").write_bytes(b"x")
    places = localize.scan_places(root)
    assert places.images == {"kitchen": ["kitchen/a.JPG", "kitchen/b.jpeg"], "office": ["office/c.Png"]}
    assert places.skipped == ["kitchen/notes.txt: not a .jpg, .jpeg or .png file",
                              "kitchen/older/: a nested folder (a place is one folder of images)",
                              "loose.jpg: a file outside any place folder"]


def test_an_empty_place_folder_or_places_folder_is_an_error(tmp_path, runs, capsys):
    root = tmp_path / "places"
    (root / "kitchen").mkdir(parents=True)
    (root / "kitchen" / "a.jpg").write_bytes(b"x")
    (root / "hall").mkdir()
    (root / "hall" / "notes.txt").write_bytes(b"x")
    code, line = run(["index", "smoke", "--places", root, "--out", tmp_path / "db"], capsys)
    assert code == 2 and line == (f"error: {root / 'hall'}: place folder 'hall' holds no image; expected one or "
                                  f"more .jpg, .jpeg or .png files in it (or remove the folder)")
    code, line = run(["index", "smoke", "--places", tmp_path / "none", "--out", tmp_path / "db"], capsys)
    assert code == 2 and line.startswith(f"error: {tmp_path / 'none'}: --places: no such folder; expected"), line
    (tmp_path / "empty").mkdir()
    code, line = run(["index", "smoke", "--places", tmp_path / "empty", "--out", tmp_path / "db"], capsys)
    assert code == 2 and line.startswith(f"error: {tmp_path / 'empty'}: --places holds no place folder"), line
    assert not (tmp_path / "db").exists()
