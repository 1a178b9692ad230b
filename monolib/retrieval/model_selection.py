"""Which epoch's model a training keeps: the selection rules compared on the training split alone.

An inner split of a study's training settings: `INNER_FAMILIES` families (both settings of each, so that no sibling
of an inner test setting is trained on) are held out as an inner test; the validation settings stay the study's;
the rest train. Each encoder of `CONFIGS` trains all `gcn.epochs` epochs once per seed, and after every epoch its
history records what a rule can read (validation leave-one-out recall@1, mean average precision, loss) and the
inner test's recall@1 under a protocol built like the paper's (`test_like_recall`: queries against their own
setting's positives and every frame of the other settings). Each rule of `RULES` is then replayed on those
histories (`EarlyStopping.advance`): the epoch it keeps, the epochs it runs, and the inner test recall@1 of the
kept model. No rule reads the study's test split; the runs of the first `TEST_CURVE_SEEDS` seeds record its
recall@1 per epoch beside, for the figure of training.md alone.

`write(study, out)` writes ``selection.md`` (the rules side by side, the winner's choice), ``selection_rules.csv``
and ``selection_curves.csv`` (every epoch of every run).
"""
from __future__ import annotations

import dataclasses
import math
import multiprocessing as mp
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd
import torch
from torch import nn

from monolib.data.protocols import family
from monolib.graphs import stage as scenegraphs
from monolib.io import write_text
from monolib.params import PAPER, Study
from monolib.retrieval import evaluate, gcn

INNER_FAMILIES = 8       # families of the training split held out as the inner test (16 settings, as the paper's)
INNER_POSITIVES = 6      # database frames per inner test setting (the paper's 6); the others query
SCENARIO = "s1"          # ground truth: the selection is about training, not about the inputs
# (method, threshold) of the encoders whose training is replayed: the paper's GCN along its threshold axis and the
# study's own encoders where the study runs them
TEST_CURVE_SEEDS = 2     # runs of the first seeds also record the study's test recall@1 per epoch (a figure only)
CONFIGS = (("gcn", 0.0), ("gcn", 1.0), ("gcn", 5.0), ("gcn", math.inf), ("ours", 0.0), ("layout", math.inf))


@dataclass(frozen=True)
class Training:
    """How the runs a rule is replayed on were trained: the learning rate, its schedule and the epochs run."""
    name: str
    lr: float
    schedule: str        # `monolib.params.SCHEDULES`
    epochs: int


# The trainings compared: the paper's constant learning rate (Adam's default 0.001), three times that, and three
# times that decayed along a half cosine over 20 epochs. Each is trained all its epochs once per seed.
TRAININGS = (Training("lr 0.001", 1e-3, "constant", 40), Training("lr 0.003", 3e-3, "constant", 40),
             Training("lr 0.003, cosine over 20", 3e-3, "cosine", 20))


@dataclass(frozen=True)
class Rule:
    name: str
    select: str          # `monolib.params.SELECT`
    min_epochs: int
    patience: int
    epochs: int          # at most this many epochs
    training: str = TRAININGS[0].name   # the `Training` whose runs it reads


RULES = (
    Rule("val recall@1, patience 6", "val_recall", 1, 6, 40),
    Rule("val recall@1, patience 40 (every epoch, best kept)", "val_recall", 1, 40, 40),
    Rule("val recall@1 from epoch 10, patience 6", "val_recall", 10, 6, 40),
    Rule("val mAP, patience 6", "val_map", 1, 6, 40),
    Rule("val mAP, patience 10", "val_map", 1, 10, 40),
    Rule("val mAP from epoch 10, patience 6", "val_map", 10, 6, 40),
    Rule("val mAP from epoch 10, patience 10", "val_map", 10, 10, 40),
    Rule("val loss, patience 6", "val_loss", 1, 6, 40),
    Rule("fixed 10 epochs (the paper's)", "last", 1, 40, 10),
    Rule("fixed 20 epochs", "last", 1, 40, 20),
    Rule("fixed 40 epochs", "last", 1, 40, 40),
    Rule("lr 0.003: val mAP from epoch 10, patience 6", "val_map", 10, 6, 40, TRAININGS[1].name),
    Rule("lr 0.003: fixed 10 epochs", "last", 1, 40, 10, TRAININGS[1].name),
    Rule("lr 0.003: fixed 15 epochs", "last", 1, 40, 15, TRAININGS[1].name),
    Rule("lr 0.003: fixed 20 epochs", "last", 1, 40, 20, TRAININGS[1].name),
    Rule("lr 0.003: fixed 40 epochs", "last", 1, 40, 40, TRAININGS[1].name),
    Rule("lr 0.003, cosine: fixed 20 epochs", "last", 1, 20, 20, TRAININGS[2].name),
)


def study_training(study: Study) -> Optional[Training]:
    """The `Training` of `TRAININGS` that is the study's own (its learning rate and schedule), if any."""
    g = study.gcn
    return next((t for t in TRAININGS if math.isclose(t.lr, g.lr) and t.schedule == g.schedule), None)


def inner_split(graphs: dict[str, list], families: int = INNER_FAMILIES, seed: int = 0) -> tuple[list, list, list]:
    """(train, val, inner test) of a scenario's cached graphs: `families` families of the training split (drawn
    with `seed`) as the inner test, the study's validation graphs as they are, the other training graphs."""
    names = sorted({family(g.setting) for g in graphs["train"]})
    if len(names) <= families:
        raise ValueError(f"{len(names)} families in the training split, need more than {families} for an inner test")
    held = set(np.random.default_rng(seed).choice(names, size=families, replace=False).tolist())
    train = [g for g in graphs["train"] if family(g.setting) not in held]
    inner = [g for g in graphs["train"] if family(g.setting) in held]
    return train, list(graphs["val"]), inner


def test_like_recall(emb: torch.Tensor, settings, positives: int = INNER_POSITIVES, seed: int = 0) -> float:
    """recall@1 of the paper's protocol on embedded frames: per setting `positives` frames (drawn with `seed`) are
    its database, the others query; a query's candidates are its own setting's positives and every frame of the
    other settings."""
    settings = np.asarray(settings)
    codes = np.unique(settings, return_inverse=True)[1].reshape(-1)
    rng = np.random.default_rng(seed)
    is_positive = np.zeros(len(codes), bool)
    for c in np.unique(codes):
        members = np.flatnonzero(codes == c)
        is_positive[rng.choice(members, size=min(positives, len(members) - 1), replace=False)] = True
    queries = np.flatnonzero(~is_positive)
    d = torch.cdist(emb[torch.from_numpy(queries)], emb)
    own = torch.from_numpy(codes[queries][:, None] == codes[None, :])
    d = d.masked_fill(own & ~torch.from_numpy(is_positive)[None, :], float("inf"))  # own queries are no candidates
    nearest = d.argmin(dim=1).numpy()
    return float((codes[nearest] == codes[queries]).mean())


_SHARED: dict = {}  # the study and its graphs while `curves` runs, for the workers it forks


def _curve(args) -> list[dict]:
    """Worker: every epoch's history row of one (method, threshold, seed) trained all its epochs with `training`."""
    method, threshold, seed, with_test, training = args
    study, split, test = _SHARED["study"], _SHARED["split"], (_SHARED["test"] if with_test else [])
    spec = dataclasses.replace(study.gcn_spec(method), patience=training.epochs + 1, select="val_recall",
                               min_epochs=1, lr=training.lr, schedule=training.schedule, epochs=training.epochs)
    projection = study.projection(SCENARIO)
    train, val, inner, test = ([gcn.encoder_graph(g, threshold, spec, projection) for g in part]
                               for part in (*split, test))
    inner_settings = [g.setting for g in inner]

    def on_epoch(model):
        row = {"inner_recall@1": test_like_recall(gcn.embed(model, inner), inner_settings, seed=study.seed)}
        if test:  # the study's own cell metric, for the figure of training.md only: no rule reads it
            result = evaluate.evaluate_protocols(gcn.embed(model, test), [g.frame for g in test],
                                                 [g.setting for g in test], study.protocol, seed)[PAPER]
            row["test_recall@1"] = result.metrics["recall@1"]
        return row

    result = gcn.train(train, val, spec, seed=seed, threads=1, deterministic=study.deterministic, on_epoch=on_epoch)
    return [{"training": training.name, "method": method, "threshold": threshold, "seed": seed, **row}
            for row in result.history]


def curves(study: Study, configs=CONFIGS, seeds: Optional[list[int]] = None, workers: Optional[int] = None,
           trainings=TRAININGS) -> pd.DataFrame:
    """Every epoch of every run of `trainings` x `configs` x `seeds` (default: the study's) on the inner split of
    `SCENARIO`. The study's own test recall@1 is recorded per epoch for the first seeds of the study's training."""
    graphs = scenegraphs.load(study, SCENARIO)
    split = inner_split(graphs, seed=study.seed)
    known = set(study.graph_methods())
    seeds = list(seeds or study.seeds)
    own = study_training(study)
    jobs = [(m, float(t), int(s), tr == own and s in seeds[:TEST_CURVE_SEEDS], tr)
            for tr in trainings for m, t in configs if m in known for s in seeds]
    _SHARED.update(study=study, split=split, test=graphs["test"])  # (forked workers inherit the graphs, unpickled)
    workers = max(1, min(workers or study.jobs, len(jobs)))
    try:
        if workers > 1:
            with mp.get_context("fork").Pool(workers) as pool:
                rows = pool.map(_curve, jobs, chunksize=1)
        else:
            rows = [_curve(j) for j in jobs]
    finally:
        _SHARED.clear()
    return pd.DataFrame([r for run in rows for r in run])


def replay(history: pd.DataFrame, rule: Rule) -> tuple[int, int]:
    """(epoch kept, epochs run) of `rule` on one run's recorded history (epochs in order)."""
    stopper = gcn.EarlyStopping(rule.patience, 0, nn.Identity(), rule.select, rule.min_epochs)
    for row in history[history["epoch"] <= rule.epochs].to_dict("records"):
        if stopper.advance(row, nn.Identity()):
            break
    return stopper.best_epoch, len(stopper.history)


def rules_table(curves_df: pd.DataFrame, rules=RULES) -> pd.DataFrame:
    """Per rule and (method, threshold): the inner test recall@1 of the kept models (mean and seed sd, in %), the
    share of runs that keep a model of epoch 1 or 2, and the mean epochs run; and the rule's row over all runs
    (``method`` ``all``: mean of the configurations' means and of their seed sds)."""
    rows = []
    for rule in rules:
        per = []
        runs = curves_df[curves_df["training"] == rule.training]
        for (m, t), g in runs.groupby(["method", "threshold"], sort=False):
            kept = []
            for _, run in g.groupby("seed", sort=True):
                run = run.sort_values("epoch")
                epoch, ran = replay(run, rule)
                kept.append((epoch, ran, float(run.loc[run["epoch"] == epoch, "inner_recall@1"].iloc[0])))
            epochs, ran, recall = (np.array(v, float) for v in zip(*kept))
            per.append((rule.name, m, t, 100 * recall.mean(), 100 * recall.std(ddof=1) if len(recall) > 1 else 0.0,
                        float((epochs <= 2).mean()), ran.mean(), len(recall)))
        if not per:
            continue
        rows += per
        p = pd.DataFrame(per)
        rows.append((rule.name, "all", math.nan, p[3].mean(), p[4].mean(), p[5].mean(), p[6].mean(), int(p[7].sum())))
    return pd.DataFrame(rows, columns=["rule", "method", "threshold", "inner_recall@1", "seed_sd", "kept_epoch_le2",
                                       "epochs_run", "runs"])


def best_possible(curves_df: pd.DataFrame) -> pd.DataFrame:
    """Per (method, threshold): the inner test recall@1 of the best epoch of each run (an oracle no rule can reach:
    it reads the inner test), mean over seeds, in %."""
    best = curves_df.groupby(["method", "threshold", "seed"], sort=False)["inner_recall@1"].max()  # any training
    return (100 * best.groupby(["method", "threshold"], sort=False).mean()).rename("oracle").reset_index()


def _threshold(t: float) -> str:
    return "∞" if math.isinf(t) else f"{t:g}"


def study_rule(study: Study, rules=RULES) -> Optional[Rule]:
    """The rule of `rules` that the study's `gcn` settings train and select by, if any."""
    g, own = study.gcn, study_training(study)
    for r in rules:
        same_stop = r.select == "last" or (r.min_epochs, r.patience) == (g.min_epochs, g.patience)
        if own and r.training == own.name and r.select == g.select and r.epochs == g.epochs and same_stop:
            return r
    return None


def markdown(table: pd.DataFrame, oracle: pd.DataFrame, study_name: str, seconds: float,
             chosen: Optional[Rule] = None) -> str:
    """selection.md: every rule over all runs, then per configuration, the oracle beside; `chosen`: the study's."""
    overall = table[table["method"] == "all"]
    trainings = "; ".join(f"{t.name} ({t.schedule}, {t.epochs} epochs)" for t in TRAININGS)
    lines = [f"**Model selection, measured on the training split of `{study_name}`** (`monolib bench --selection`, "
             f"{seconds:.0f} s). {INNER_FAMILIES} training families held out as an inner test (both settings each), "
             f"queried as the paper's protocol queries its test ({INNER_POSITIVES} positives per setting, the other "
             f"frames query, every frame of the other settings a candidate); the study's validation settings as "
             f"they are; each encoder trained all its epochs once per seed and training ({trainings}), each rule "
             f"replayed on the recorded epochs of its training (rules without a learning rate: 0.001). Inner "
             f"recall@1 in %; seed sd: standard deviation over seeds, mean over configurations; epoch 1-2: share of "
             f"runs whose kept model is from epoch 1 or 2.", "",
             "| rule | inner recall@1 | seed sd | epoch 1-2 | epochs run |", "|---|---:|---:|---:|---:|"]
    for _, r in overall.iterrows():
        lines.append(f"| {r['rule']} | {r['inner_recall@1']:.1f} | {r['seed_sd']:.1f} | {r['kept_epoch_le2']:.2f} | "
                     f"{r['epochs_run']:.1f} |")
    configs = table[table["method"] != "all"][["method", "threshold"]].drop_duplicates()
    lines += ["", "Per encoder (inner recall@1, mean ± seed sd; oracle: the best epoch of each run, read off the "
              "inner test):", "",
              "| rule | " + " | ".join(f"`{m}` {_threshold(t)}" for m, t in configs.itertuples(index=False)) + " |",
              "|---|" + "---:|" * len(configs)]
    for name, g in table[table["method"] != "all"].groupby("rule", sort=False):
        cells = [f"{r['inner_recall@1']:.1f} ± {r['seed_sd']:.1f}" for _, r in g.iterrows()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    orc = {(m, t): v for m, t, v in oracle.itertuples(index=False)}
    lines.append("| oracle | " + " | ".join(f"{orc[(m, t)]:.1f}" for m, t in configs.itertuples(index=False)) + " |")
    if chosen is not None:
        lines += ["", f"The study trains by the rule **{chosen.name}** (its `gcn` settings)."]
    return "\n".join(lines) + "\n"


def write(study: Study, out: Path, seeds: Optional[list[int]] = None) -> dict[str, Path]:
    """Run the comparison on `study`'s training split and write its files into `out`."""
    import time

    t = time.perf_counter()
    df = curves(study, seeds=seeds)
    table = rules_table(df)
    seconds = time.perf_counter() - t
    out = Path(out)
    files = {"md": out / "selection.md", "rules": out / "selection_rules.csv", "curves": out / "selection_curves.csv"}
    write_text(files["curves"], df.to_csv(index=False))
    write_text(files["rules"], table.to_csv(index=False))
    write_text(files["md"], markdown(table, best_possible(df), study.name, seconds, study_rule(study)))
    return files
