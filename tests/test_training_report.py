"""figures/training.md: how training ended, per method, scenario and threshold, and the targets it is held to."""
import math

import pandas as pd
import pytest

from monolib.report import training


def cells(rows):
    return pd.DataFrame(rows, columns=["method", "scenario", "threshold", "seed", "best_epoch", "epochs_run",
                                       "recall@1"])


def test_the_table_counts_early_models_and_the_seed_spread():
    c = cells([("gcn", "s1", 0.0, s, e, e + 6, r) for s, (e, r) in enumerate([(12, 70.0), (15, 72.0), (20, 74.0)])]
              + [("gcn", "s1", 1.0, s, e, e + 6, r) for s, (e, r) in enumerate([(1, 30.0), (2, 80.0), (14, 55.0)])])
    t = training.training_table(c)
    at0, at1, whole = (t[t.threshold == 0.0].iloc[0], t[t.threshold == 1.0].iloc[0], t[t.threshold.isna()].iloc[0])
    assert (at0.seeds, at0.best_epoch_median, at0.best_epoch_min, at0.best_epoch_max) == (3, 15, 12, 20)
    assert at0["recall@1_seed_sd"] == pytest.approx(2.0) and at0["recall@1_se"] == pytest.approx(2 / math.sqrt(3))
    assert at0.kept_early == 0 and at1.kept_early == pytest.approx(2 / 3)
    assert at1["recall@1_seed_sd"] == pytest.approx(25.0)
    assert whole["recall@1_seed_sd"] == pytest.approx(25.0) and whole.kept_early == pytest.approx(1 / 3)
    md = training.markdown(t, "toy")
    assert "| `gcn` | s1 | 1 | 3 | 8 [7, 20] | 2 [1, 14] | 0.67 | 55.0 | 25.0 | 14.4 |" in md
    assert "1 of 2 cells (over: `gcn` s1 1 m 25.0)" in md
    assert "`gcn` 0.33 (over)" in md
    assert "1 of 2 cells (over: `gcn` s1 1 m, 14.4 with 3 seeds, 70 at its spread;" in md
    assert training.seeds_needed(8.7) == 9 and training.seeds_needed(6.0) == 4 and training.seeds_needed(1.0) == 2


def test_a_study_that_meets_its_targets_says_so():
    c = cells([("layout", "s2", math.inf, s, 12 + s, 18 + s, 80.0 + s) for s in range(5)])
    md = training.markdown(training.training_table(c), "toy")
    assert "1 of 1 cells." in md and "`layout` 0.00." in md and "(over" not in md


def test_cells_are_read_in_the_percent_they_hold(tmp_path, monkeypatch):
    """A cell.json holds recall@1 in %, as the tables print it; the training table reads it as it is, so its means
    and spreads are on the tables' scale (a cell copied from a smaller threshold counts once)."""
    from monolib import io, paths

    monkeypatch.setattr(paths, "RUNS", tmp_path)
    for seed, recall in enumerate([70.0, 74.0]):
        cell = {"method": "gcn", "scenario": "s1", "threshold": 1.0, "seed": seed, "best_epoch": 12, "epochs_run": 18,
                "metrics": {"paper": {"recall@1": recall}}}
        io.write_json(tmp_path / "study" / "cells" / "gcn" / f"s1__t1__s{seed}" / "cell.json", cell)
    io.write_json(tmp_path / "study" / "cells" / "gcn" / "s1__t2__s0" / "cell.json",
                  {"method": "gcn", "scenario": "s1", "threshold": 2.0, "seed": 0, "best_epoch": 12, "epochs_run": 18,
                   "same_graphs_as": "s1__t1__s0", "metrics": {"paper": {"recall@1": 70.0}}})
    read = training.training_cells("study")
    assert sorted(read["recall@1"]) == [70.0, 74.0]
    row = training.training_table(read).iloc[0]
    assert row["recall@1_mean"] == pytest.approx(72.0) and row["recall@1_seed_sd"] == pytest.approx(2 ** 1.5)
