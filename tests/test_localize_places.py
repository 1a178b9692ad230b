"""The localizer on the finished smoke study, as a user runs it: the front page's commands exactly as written (the
study's name `quick` read as `smoke`), a folder of one's own places indexed (and indexed again: only new images
embedded), a database that stands on its own (the study's runs/ out of reach, the folder copied elsewhere), the
figure of what it saw, and the tonemapped twin a study of HDR node colours trains for it. The "photos" are the
smoke study's tonemapped test frames written as JPEG (`localize.example_photos`)."""
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
import yaml
from PIL import Image

from monolib import cli, localize, paths
from monolib.params import load_study

pytestmark = [pytest.mark.slow, pytest.mark.shares_runs]  # the finished smoke study (`smoke_study`)
ENV = {**os.environ, "MPLBACKEND": "agg", "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def photos(smoke_study, tmp_path_factory):
    """(places folder, query files) of the smoke study's test settings as JPEG photos."""
    return localize.example_photos(load_study("smoke"), tmp_path_factory.mktemp("photos"))


def front_page_commands() -> list[str]:
    """The README's own-photos commands: the table row that localizes an image and the bullet of your own
    photos, each a shell line of `.venv/bin/monolib` calls."""
    text = (paths.ROOT / "README.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| localize"))
    bullet = text[text.index("- **Your own photos"):].split("\n- ")[0]
    bullet = " ".join(line.strip() for line in bullet.splitlines())
    commands = re.findall(r"`(\.venv/bin/monolib [^`]+)`", row) + re.findall(r"`(\.venv/bin/monolib [^`]+)`", bullet)
    assert len(commands) == 3, commands
    return commands


def test_the_front_pages_commands_as_written(photos, tmp_path):
    """Run in a folder of the user's: `.venv` there, a photo.jpg and a folder of places my_places/."""
    places, queries = photos
    (tmp_path / ".venv").symlink_to(paths.ROOT / ".venv")
    shutil.copy(queries[0], tmp_path / "photo.jpg")
    shutil.copytree(places, tmp_path / "my_places")
    for command in front_page_commands():
        line = re.sub(r"\bquick\b", "smoke", command)
        out = subprocess.run(line, shell=True, cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, (line, out.stdout[-2000:], out.stderr[-2000:])
    assert (tmp_path / "seen.png").is_file() and (tmp_path / "my_db" / "meta.json").is_file()
    meta = json.loads((tmp_path / "my_db" / "meta.json").read_text())
    assert meta["places"] == str((tmp_path / "my_places").resolve()) and meta["frames"] == len(queries)


def test_your_own_places_indexed_again_embed_only_what_is_new(photos, tmp_path, capsys):
    places, queries = photos
    mine = tmp_path / "places"
    shutil.copytree(places, mine)
    db = tmp_path / "db"
    assert cli.main(["index", "smoke", "--places", str(mine), "--out", str(db)]) == 0
    printed = capsys.readouterr().out
    n = len(queries)
    assert f"index: {n} images of {n} places in {mine}: {n} embedded, 0 unchanged" in printed, printed
    assert "node colours tonemapped" in printed and "the places of" in printed
    emb = np.load(db / "embeddings.npy")
    # a new image of a place (a query rotated on its side by EXIF, as a phone stores it), a note and a nested folder
    first = sorted(p.name for p in mine.iterdir())[0]
    exif = Image.Exif()
    exif[0x0112] = 8
    Image.open(queries[-1]).transpose(Image.Transpose.ROTATE_270).save(mine / first / "NEW.JPG", exif=exif)
    (mine / first / "notes.txt").write_text("the kitchen")
    (mine / first / "old").mkdir()
    assert cli.main(["index", "smoke", "--places", str(mine), "--out", str(db)]) == 0
    printed = capsys.readouterr().out
    assert f"{n + 1} images of {n} places in {mine}: 1 embedded, {n} unchanged" in printed, printed
    assert f"{first}/notes.txt: not a .jpg, .jpeg or .png file" in printed and f"{first}/old/: a nested" in printed
    meta, frames, emb2 = localize.read_database(db)
    assert meta["skipped"] == [f"{first}/notes.txt: not a .jpg, .jpeg or .png file",
                               f"{first}/old/: a nested folder (a place is one folder of images)"]
    kept = frames["frame"] != f"{first}/NEW.JPG"
    np.testing.assert_array_equal(emb2[kept.to_numpy()], emb)
    # each query finds its own place first, and --json names the matched image and its file
    assert cli.main(["localize", *map(str, queries), "--db", str(db), "--k", "2", "--json"]) == 0
    results = json.loads(capsys.readouterr().out)
    # the last query's own pixels, stored on their side with an EXIF orientation, now sit in the first place:
    # read upright, they are its nearest image
    assert results[-1]["matches"][0]["image"] == f"{first}/NEW.JPG", results[-1]
    # one image per place of the smoke study's briefly trained networks: better than chance (1 in n), not more
    right = sum(r["matches"][0]["place"] == q.stem for r, q in zip(results[:-1], queries))
    assert right >= 2, results
    m = results[0]["matches"][0]
    assert m["image"].startswith(m["place"] + "/") and m["path"] == str(mine.resolve() / m["image"])


def test_a_database_stands_on_its_own(photos, tmp_path, capsys, monkeypatch):
    """Built from the study, then queried with runs/ out of reach (MONOLIB_RUNS of an empty folder, another
    process) from a copy of the folder: the same answers, and a figure of what it saw."""
    places, queries = photos
    db = tmp_path / "db"
    assert cli.main(["index", "smoke", "--out", str(db)]) == 0
    capsys.readouterr()
    assert cli.main(["localize", *map(str, queries), "--db", str(db), "--json"]) == 0
    here = json.loads(capsys.readouterr().out)
    copy = tmp_path / "elsewhere" / "db"
    shutil.copytree(db, copy)
    shutil.rmtree(db)
    env = {**ENV, "MONOLIB_RUNS": str(tmp_path / "no_runs"), "MONOLIB_FIGURES": str(tmp_path / "no_figures")}
    out = subprocess.run([sys.executable, "-m", "monolib.cli", "localize", *map(str, queries), "--db", str(copy),
                          "--json", "--show", str(tmp_path / "seen.png")], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    there = json.loads(out.stdout)
    assert not (tmp_path / "no_runs").exists() or not any((tmp_path / "no_runs").rglob("*.pt"))
    for a, b in zip(here, there):
        assert [(m["place"], m["image"]) for m in a["matches"]] == [(m["place"], m["image"]) for m in b["matches"]]
        np.testing.assert_allclose([m["distance"] for m in a["matches"]], [m["distance"] for m in b["matches"]],
                                   rtol=1e-5)
    figures = [tmp_path / f"seen-{i + 1}.png" for i in range(len(queries))]
    assert [b["figure"] for b in there] == [str(f) for f in figures] and all(f.stat().st_size > 10_000 for f in figures)


def test_a_study_of_hdr_colours_trains_the_tonemapped_twin_once(photos, tmp_path, capsys):
    """The smoke study with every scenario's node colours HDR (as quick's): `index` names the HDR cell, trains
    its tonemapped twin once into runs/<study>/localizer/, and says so in meta.json; a second index reuses it."""
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["scenarios"]["s3"].pop("colour")
    path = tmp_path / "smoke_hdr.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    study = load_study(path)
    twin_study, record = localize.pick(study)
    assert record["scenario"].endswith("_tonemapped") and twin_study.colour(record["scenario"]) == "tonemapped"
    assert record["folder"].startswith(str(paths.study_dir("smoke") / "localizer" / "cells"))
    source = study.scenarios[record["scenario"].removesuffix("_tonemapped")]
    assert (source.depth, source.semantic) == (twin_study.scenarios[record["scenario"]].depth,
                                               twin_study.scenarios[record["scenario"]].semantic)
    capsys.readouterr()
    db = tmp_path / "db"
    assert cli.main(["index", str(path), "--places", str(photos[0]), "--out", str(db)]) == 0
    printed = capsys.readouterr().out
    assert "reads HDR node colours; using its tonemapped twin, trained earlier" in printed, printed
    meta = json.loads((db / "meta.json").read_text())
    assert meta["colour"] == "tonemapped" and meta["twin_of"] == record["twin_of"] and meta["cell"] == record["folder"]
    assert f"trained for the localizer as the tonemapped twin of {record['twin_of']}" in printed


def test_the_notebook_through_papermill_from_another_folder(smoke_study, tmp_path):
    """notebooks/localize.ipynb at its defaults (the smoke study, JPEG photos of its test settings), run by
    papermill from another working directory: its checked line and one figure per query."""
    papermill = os.path.join(os.path.dirname(sys.executable), "papermill")
    out = subprocess.run([papermill, str(paths.NOTEBOOKS / "localize.ipynb"), "out.ipynb", "-p", "work",
                          str(tmp_path / "work")], cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, (out.stdout + out.stderr)[-3000:]
    cells = json.loads((tmp_path / "out.ipynb").read_text())["cells"]
    printed = "".join(t for c in cells for o in c.get("outputs", []) for t in o.get("text", []))
    assert "6 places, 6 images, 6 queries, k 3, node colours tonemapped" in printed, printed
    images = [o for c in cells for o in c.get("outputs", []) if "image/png" in o.get("data", {})]
    assert len(images) == 6
