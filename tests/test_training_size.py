"""The training-size report (`monolib.report.training_size`) on the committed studies' own files, copied into a
figures folder of its own: what it reads, what it leaves out, and the README's reproduction table."""
from __future__ import annotations

import math
import shutil

import pandas as pd
import pytest

from monolib import paths
from monolib.report import training_size


@pytest.fixture
def figures(tmp_path, monkeypatch):
    """A figures folder holding the committed quick, real and real_full results (the files the report reads)."""
    for name, files in (("quick", ["intervals.csv"]), ("real", ["intervals.csv"]),
                        ("real_full", ["intervals.csv", "real_vs_synth.csv"])):
        src, dst = paths.figures_dir(name), tmp_path / paths.COMMITTED_FIGURES[name]
        dst.mkdir(parents=True, exist_ok=True)
        for f in files:
            shutil.copy(src / f, dst / f)
    monkeypatch.setattr(paths, "FIGURES", tmp_path)
    return tmp_path


def _recall1(path, method, threshold):
    iv = pd.read_csv(path)
    iv = iv[(iv["scenario"] == "s1") & (iv["metric"] == "recall") & (iv["k"] == 1) & (iv["protocol"] == "paper")]
    return iv[(iv["method"] == method) & (iv["threshold"].astype(float) == threshold)].iloc[0]


def test_the_curve_holds_each_studys_own_numbers_and_names_the_missing_ones(figures):
    written = training_size.write(figures)
    t = pd.read_csv(written["training_size_csv"])
    assert set(t["study"]) == {"quick", "real", "real_full"}
    assert set(t.loc[t["study"] == "real_full", "size"]) == {"all x 100"}
    for r in t.itertuples():
        src = figures / paths.COMMITTED_FIGURES[r.study] / "intervals.csv"
        assert r.mean == pytest.approx(float(_recall1(src, r.method, r.threshold)["mean"]))
    # every row of ROWS on the real leg at both sizes; the paper's number beside the GCN's thresholds only
    assert len(t[t["leg"] == "real folds"]) == 2 * len(training_size.ROWS)
    assert t.loc[(t["method"] == "gcn") & (t["threshold"] == 1.0), "paper"].notna().all()
    assert t.loc[t["method"] != "gcn", "paper"].isna().all()
    text = written["training_size"].read_text()
    assert "Not run yet (left out): `quick_96x40`, `paper_scale`, `real_96x40`." in text
    assert written["training_size_png"].stat().st_size > 0
    assert "reproduces" not in written  # the mini-Hypersim at the paper's size is missing


def test_the_reproduction_table_sets_the_paper_scale_beside_quick(figures):
    """With paper_scale's results there (here: quick's file with every mean 3 points up), reproduces.md has a
    column for each end of both legs, and the curve a third size on the mini-Hypersim."""
    iv = pd.read_csv(figures / "intervals.csv")
    iv["mean"] += 3.0
    (figures / "paper_scale").mkdir()
    iv.to_csv(figures / "paper_scale" / "intervals.csv", index=False)
    written = training_size.write(figures)
    table = written["reproduces"].read_text()
    assert ("| threshold (m) | paper | real folds, 48 x 20 | real folds, all x 100 | mini-Hypersim, 48 x 20 | "
            "mini-Hypersim, 144 x 60 |") in table
    quick_inf = float(_recall1(figures / "intervals.csv", "gcn", math.inf)["mean"])
    row = next(line for line in table.splitlines() if line.startswith("| ∞ |"))
    assert f"{quick_inf:.1f} [" in row and f"{quick_inf + 3:.1f} [" in row
    t = pd.read_csv(written["training_size_csv"])
    assert list(dict.fromkeys(t.loc[t["leg"] == "mini-Hypersim", "size"])) == ["48 x 20", "144 x 60"]


def test_where_the_papers_number_lies_is_counted_per_column():
    """`paper_inside` puts each of the paper's thresholds inside, below or above a column's interval, from the
    paper's own Table 1 (1 m: 94.3, 2 m: 90.9, 5 m: 80.2, 10 m: 91.4, inf: 93.5)."""
    rows = pd.DataFrame({"method": "gcn", "threshold": [0.0, 1.0, 2.0, 5.0, 10.0, math.inf],
                         "ci_lo": [0.0, 90.0, 92.0, 70.0, 70.0, 90.0], "ci_hi": [100.0, 99.0, 99.0, 79.0, 95.0, 99.0]})
    text = training_size.paper_inside([("a column", rows), ("another", rows.iloc[:0])])
    assert "- a column: inside the interval at 3 of 5 thresholds; the paper's above it at 5 m; " \
           "the paper's below it at 2 m." in text
    assert "- another: inside the interval at 0 of 0 thresholds." in text
