"""The model-selection bench's bookkeeping: each rule replayed on the runs of its own training, and the study's rule."""
import pandas as pd
import pytest

from monolib.params import load_study
from monolib.retrieval.model_selection import RULES, TRAININGS, recommend, rules_table, study_rule, study_training


pytestmark = pytest.mark.shares_runs


def histories(peaks: dict[str, int], seeds: int = 3, epochs: int = 40) -> pd.DataFrame:
    """Runs whose validation mAP peaks at `peaks[training]` and whose inner recall@1 is the epoch / 100."""
    rows = [{"training": training, "method": "gcn", "threshold": 0.0, "seed": seed, "epoch": e,
             "val_map": -float((e - peak) ** 2), "val_recall@1": 0.5, "val_loss": 1.0, "inner_recall@1": e / 100}
            for training, peak in peaks.items() for seed in range(seeds) for e in range(1, epochs + 1)]
    return pd.DataFrame(rows)


def test_each_rule_reads_the_runs_of_its_own_training():
    by_name = {r.name: r for r in RULES}
    rules = [by_name[n] for n in ("val mAP, patience 6", "fixed 20 epochs",
                                  "lr 0.003: val mAP from epoch 10, patience 6",
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
    assert (overall.loc["fixed 20 epochs", "seed_sd"] == pytest.approx(0.0, abs=1e-9)
            and overall.loc["fixed 20 epochs", "runs"] == 3)


def test_the_study_rule_is_the_one_its_gcn_settings_train_by():
    quick = load_study("quick", check_files=False)
    assert study_training(quick) == TRAININGS[1]
    assert study_rule(quick).name == "lr 0.003: fixed 20 epochs"
    smoke = load_study("smoke", check_files=False)  # 3 epochs: no rule of the bench
    assert study_training(smoke) == TRAININGS[0] and study_rule(smoke) is None


def test_the_image_encoders_are_compared_in_groups_of_their_own():
    """A rule's row over all runs is taken per group: the graph encoders together, each learned image encoder
    alone; the study's rule of each is the one its `image_training` trains by."""
    runs = histories({"lr 0.001": 2})
    image = histories({"lr 0.001": 30}).assign(method="image_triplet", threshold=float("inf"))
    table = rules_table(pd.concat([runs, image]), [r for r in RULES if r.name == "fixed 20 epochs"])
    overall = table[table["method"] == "all"].set_index("group")
    assert sorted(overall.index) == ["graph", "image_triplet"]
    assert overall.loc["graph", "runs"] == 3 and overall.loc["image_triplet", "runs"] == 3
    quick = load_study("quick", check_files=False)
    for m in ("image_triplet", "imagenet_triplet"):
        spec = quick.gcn_spec(m)
        rule = study_rule(quick, m)
        assert rule is not None and rule.epochs == spec.epochs and study_training(quick, m).lr == spec.lr


@pytest.mark.slow
def test_runs_of_every_encoder_are_recorded_per_epoch_and_resumed(smoke_study):
    """`curves` on the smoke study (one family held out): a graph encoder and both image encoders trained two
    epochs each, every epoch recorded with its inner test recall@1; each run written to its file, and a second
    call reads the files instead of training again."""
    import math

    from monolib.retrieval import model_selection as ms

    study = load_study("smoke")
    training = ms.Training("smoke test", 1e-3, "constant", 2, (ms.GRAPH, "image_triplet", "imagenet_triplet"))
    configs = (("gcn", 1.0), ("image_triplet", math.inf), ("imagenet_triplet", math.inf))
    for job in [(m, t, 0, curve, training) for m, t in configs for curve in (False, True)]:
        ms.run_path(study, job, 1).unlink(missing_ok=True)  # (a run with its curve, left by an earlier session, too)
    df = ms.curves(study, configs, seeds=[0], workers=1, trainings=(training,), families=1)
    assert sorted(df["method"].unique()) == ["gcn", "image_triplet", "imagenet_triplet"]
    assert (df.groupby("method")["epoch"].apply(list) == [[1, 2]] * 3).all()
    assert df["inner_recall@1"].between(0, 1).all() and df["val_loss"].notna().all()
    path = ms.run_path(study, ("imagenet_triplet", math.inf, 0, False, training), 1)
    marked = pd.read_csv(path).assign(**{"inner_recall@1": 0.123})
    marked.to_csv(path, index=False)
    again = ms.curves(study, configs, seeds=[0], workers=1, trainings=(training,), families=1)
    assert (again.loc[again["method"] == "imagenet_triplet", "inner_recall@1"] == 0.123).all()
    pd.testing.assert_frame_equal(again[again["method"] != "imagenet_triplet"].reset_index(drop=True),
                                  df[df["method"] != "imagenet_triplet"].reset_index(drop=True))
    # a run asked for without its test curve reads the same training recorded with it (the curve changes nothing)
    curved = ms.run_path(study, ("gcn", 1.0, 0, True, training), 1)
    plain = ms.run_path(study, ("gcn", 1.0, 0, False, training), 1)
    plain.rename(curved)
    pd.read_csv(curved).assign(**{"test_recall@1": 0.5, "inner_recall@1": 0.321}).to_csv(curved, index=False)
    reused = ms.curves(study, configs[:1], seeds=[0], workers=1, trainings=(training,), families=1)
    assert (reused["inner_recall@1"] == 0.321).all() and "test_recall@1" not in reused.columns
    assert not plain.exists()  # read, not trained again


def test_the_criterion_chooses_the_lowest_spread_among_the_best_and_names_those_level_with_it():
    rows = [("a", 60.0, 4.0, 20), ("b", 59.5, 2.0, 20), ("c", 59.2, 2.8, 20), ("d", 58.0, 0.5, 20),
            ("e", 70.0, 0.1, 40)]
    table = pd.DataFrame([{"rule": r, "group": "graph", "method": "all", "inner_recall@1": rec, "seed_sd": sd,
                           "epochs_run": ep} for r, rec, sd, ep in rows])
    assert recommend(table, "graph") == ["b", "c"]  # e: over the budget; d: a point and a half below the best
    assert recommend(table.assign(group="image_triplet"), "image_triplet") == ["e"]  # no budget: every rule
    assert recommend(table, "imagenet_triplet") == []


def test_the_committed_comparison_chose_the_rule_each_encoder_of_quick_trains_by():
    """figures/selection.md's table: each group's rule in quick (`gcn:` and `image_training`) is the one the
    criterion chooses or one level with it."""
    from pathlib import Path

    from monolib import paths

    path = Path(paths.ROOT) / "figures" / "selection_rules.csv"
    if not path.is_file():
        pytest.skip("figures/selection_rules.csv not written (make bench-selection)")
    table = pd.read_csv(path)
    quick = load_study("quick", check_files=False)
    for method, grp in (("gcn", "graph"), ("image_triplet", "image_triplet"), ("imagenet_triplet", "imagenet_triplet")):
        assert study_rule(quick, method).name in recommend(table, grp), method


def test_real_full_trains_by_the_rule_chosen_at_its_own_size():
    """figures/real_full/selection.md's table (the rules at the development set's full training size, on fold 0's
    training side): params/real_full.yaml trains every graph encoder by the rule the criterion chooses there."""
    from monolib import paths

    table = pd.read_csv(paths.figures_dir("real_full") / "selection_rules.csv")
    real_full = load_study("real_full", check_files=False)
    assert set(table["group"]) == {"graph"}  # no image encoder on published graphs
    for method in real_full.graph_methods():
        assert study_rule(real_full, method).name == recommend(table, "graph")[0], method
