"""`monolib bench localize` on the finished smoke study, at a small size: the page and the CSV it writes (which
methods, which numbers, how many queries), the recall numbers percentages computed by the bench, the latency
measured over the images asked for."""
import pandas as pd
import pytest

from monolib import localize, methods
from monolib.bench import photos
from monolib.params import load_study

pytestmark = [pytest.mark.slow, pytest.mark.shares_runs]  # the finished smoke study (`smoke_study`)


def test_the_localize_bench_writes_its_page_and_csv(smoke_study, tmp_path):
    out = tmp_path / "figures" / "localize.md"
    record = photos.localize_photos("smoke", out=out, latency_images=40)
    study = load_study("smoke")
    page, table = out.read_text(), pd.read_csv(out.with_suffix(".csv"))

    default = localize.pick_cell(study, train=False)
    image_methods = [m for m in study.methods if methods.kind(m, study) == "image"]
    assert table["method"].tolist() == [default["method"], *image_methods]
    assert table["default"].tolist() == [True] + [False] * len(image_methods)
    protocol = study.protocol
    assert (table["queries"] == protocol.settings * protocol.queries).all()
    assert (table["positives"] == protocol.settings * protocol.positives).all()
    recalls = ["recall@1_study", "recall@1_study_rescored", "recall@1_photo", "recall@1_places_study",
               "recall@1_places_photo"]
    assert table[recalls].apply(lambda c: c.between(0, 100)).all().all()
    # the study's-frames column is the cell's own number, and the bench's scoring of the same rows reproduces it
    assert table["recall@1_study"].iloc[0] == pytest.approx(default["metrics"]["paper"]["recall@1"], abs=0.01)
    assert (table["recall@1_study_rescored"] - table["recall@1_study"]).abs().max() < 0.01
    # at least the images asked for, even where the protocol holds fewer frames
    assert (table["latency_images"] >= 40).all()
    assert (table["latency_p90_ms"] >= table["latency_median_ms"]).all() and (table["latency_median_ms"] > 0).all()

    assert page.startswith("# Localizing photos: recall@1 and latency\n")
    for heading in ("## Recall@1: the study's frames against the same frames as photos", "## Latency of one image"):
        assert f"\n{heading}\n" in page
    assert record["cpu"] in page and f"{record['cores']} cores" in page and record["date"] in page
    rows = [line for line in page.splitlines() if line.startswith(f"| `{default['method']}`")]
    assert len(rows) == 2  # one in each table
    recall_row = rows[0].split(" | ")
    assert f"{table['recall@1_study'].iloc[0]:.1f}" == recall_row[3]
    assert f"{table['recall@1_photo'].iloc[0]:.1f}" == recall_row[4]
    assert f"{protocol.settings * protocol.queries}" == recall_row[2]
