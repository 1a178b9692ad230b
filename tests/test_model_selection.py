"""The model-selection bench's bookkeeping: each rule replayed on the runs of its own training, and the study's rule."""
import pandas as pd
import pytest

from monolib.params import load_study
from monolib.retrieval.model_selection import RULES, TRAININGS, rules_table, study_rule, study_training


def histories(peaks: dict[str, int], seeds: int = 3, epochs: int = 40) -> pd.DataFrame:
    """Runs whose validation mAP peaks at `peaks[training]` and whose inner recall@1 is the epoch / 100."""
    rows = [{"training": training, "method": "gcn", "threshold": 0.0, "seed": seed, "epoch": e,
             "val_map": -float((e - peak) ** 2), "val_recall@1": 0.5, "val_loss": 1.0, "inner_recall@1": e / 100}
            for training, peak in peaks.items() for seed in range(seeds) for e in range(1, epochs + 1)]
    return pd.DataFrame(rows)


def test_each_rule_reads_the_runs_of_its_own_training():
    by_name = {r.name: r for r in RULES}
    rules = [by_name[n] for n in ("val mAP, patience 6", "fixed 20 epochs", "lr 0.003: val mAP from epoch 10, patience 6",
                                  "lr 0.003: fixed 15 epochs", "lr 0.003, cosine: fixed 20 epochs")]
    table = rules_table(histories({"lr 0.001": 2, "lr 0.003": 15}), rules)
    row = table[table["method"] == "gcn"].set_index("rule")
    assert row.loc["val mAP, patience 6", "inner_recall@1"] == pytest.approx(2.0)  # kept at the peak, epoch 2
    assert row.loc["val mAP, patience 6", "kept_epoch_le2"] == 1.0
    assert row.loc["val mAP, patience 6", "epochs_run"] == 8  # 6 epochs without a better one after epoch 2
    assert row.loc["fixed 20 epochs", "inner_recall@1"] == pytest.approx(20.0)
    assert row.loc["lr 0.003: val mAP from epoch 10, patience 6", "inner_recall@1"] == pytest.approx(15.0)
    assert row.loc["lr 0.003: fixed 15 epochs", "epochs_run"] == 15
    assert "lr 0.003, cosine: fixed 20 epochs" not in row.index  # no run of that training: no row, no error
    overall = table[table["method"] == "all"].set_index("rule")
    assert overall.loc["fixed 20 epochs", "seed_sd"] == pytest.approx(0.0, abs=1e-9) and overall.loc["fixed 20 epochs", "runs"] == 3


def test_the_study_rule_is_the_one_its_gcn_settings_train_by():
    quick = load_study("quick", check_files=False)
    assert study_training(quick) == TRAININGS[1]
    assert study_rule(quick).name == "lr 0.003: fixed 20 epochs"
    smoke = load_study("smoke", check_files=False)  # 3 epochs: no rule of the bench
    assert study_training(smoke) == TRAININGS[0] and study_rule(smoke) is None
