"""How the trained encoders are trained and which epoch's model they keep: rules compared on the training split alone.

An inner split of a study's training settings: `INNER_FAMILIES` families (both settings of each, so that no sibling
of an inner test setting is trained on) are held out as an inner test; the validation settings stay the study's;
the rest train. A study of folds by volume (published graphs) holds out as many volumes of fold 0's training side as
that fold tests (`inner_families`), and its image encoders are not compared (there are no frames). Each encoder of
`CONFIGS` (the graph encoders on the scene graphs of `SCENARIO`, the learned image encoders on the same settings'
frames) trains all the epochs of each `TRAININGS` entry that trains it, once per seed, and after every epoch its history
records what a rule can read (validation leave-one-out recall@1, mean average precision, loss) and the inner test's
recall@1 under a protocol built like the paper's (`test_like_recall`: queries against their own setting's positives and
every frame of the other settings). Each rule of `RULES` is then replayed on those histories (`EarlyStopping.advance`):
the epoch it keeps, the epochs it runs, and the inner test recall@1 of the kept model. No rule reads the study's test
split; the runs of the first `TEST_CURVE_SEEDS` seeds of each encoder's own training record its recall@1 per epoch
beside, for the figure of training.md alone.

Each run is kept in ``runs/<study>/selection/`` under a key of what it computes (`run_key`), so that a stopped
comparison resumes where it was. `write(study, out)` writes ``selection.md`` (the rules side by side, per group of
encoders: the graph encoders together, each image encoder alone, and the study's choice of each),
``selection_rules.csv`` and ``selection_curves.csv`` (every epoch of every run).
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

from monolib import methods, paths, versions
from monolib.data import dataset, selection
from monolib.data.protocols import family
from monolib.graphs import scenegraphs
from monolib.io import write_text
from monolib.params import PAPER, TRAINED_IMAGE_METHODS as TRAINED_IMAGE, Study, key_of
from monolib.perception import features
from monolib.retrieval import baselines, cell, evaluate, gcn, pretrained
from monolib.retrieval.training import EarlyStopping, training_rule

INNER_FAMILIES = 8       # families of the training split held out as the inner test (16 settings, as the paper's)
INNER_POSITIVES = 6      # database frames per inner test setting (the paper's 6); the others query
SCENARIO = "s1"          # ground truth: the selection is about training, not about the inputs
TEST_CURVE_SEEDS = 2     # runs of the first seeds also record the study's test recall@1 per epoch (a figure only)
# (method, threshold) of the encoders whose training is replayed: the paper's GCN along its threshold axis, the
# study's own graph encoders where the study runs them, and the two learned image encoders (their threshold: none)
CONFIGS = (("gcn", 0.0), ("gcn", 1.0), ("gcn", 5.0), ("gcn", math.inf), ("ours", 0.0), ("layout", math.inf),
           ("image_triplet", math.inf), ("imagenet_triplet", math.inf))
GRAPH = "graph"          # the group of every graph encoder in `Training.trains` and the tables


@dataclass(frozen=True)
class Training:
    """How the runs a rule is replayed on were trained: the learning rate, its schedule, the epochs run, and which
    encoders it trains (`GRAPH`: every graph encoder; else image methods by name)."""
    name: str
    lr: float
    schedule: str        # `monolib.params.SCHEDULES`
    epochs: int
    trains: tuple = (GRAPH,)


# The trainings compared: the paper's constant learning rate (Adam's default 0.001), three times that, and three
# times that decayed along a half cosine over 20 epochs; for the ImageNet head, which starts trained, also 0.0003
# (pretrained layers are fine-tuned at a smaller rate). Each is trained all its epochs once per seed.
TRAININGS = (Training("lr 0.001", 1e-3, "constant", 40, (GRAPH, "image_triplet", "imagenet_triplet")),
             Training("lr 0.003", 3e-3, "constant", 40, (GRAPH, "image_triplet")),
             Training("lr 0.003, cosine over 20", 3e-3, "cosine", 20),
             Training("lr 0.0003", 3e-4, "constant", 40, ("imagenet_triplet",)))


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
    Rule("fixed 30 epochs", "last", 1, 40, 30),
    Rule("lr 0.003: fixed 30 epochs", "last", 1, 40, 30, TRAININGS[1].name),
    Rule("lr 0.003: val loss, patience 6", "val_loss", 1, 6, 40, TRAININGS[1].name),
    Rule("lr 0.0003: val mAP from epoch 10, patience 6", "val_map", 10, 6, 40, TRAININGS[3].name),
    Rule("lr 0.0003: val loss, patience 6", "val_loss", 1, 6, 40, TRAININGS[3].name),
    *(Rule(f"lr 0.0003: fixed {n} epochs", "last", 1, 40, n, TRAININGS[3].name) for n in (10, 20, 30, 40)),
)


def group(method: str) -> str:
    """The group a method's runs are compared in: each learned image encoder alone, every graph encoder (the
    paper's and the study's variants) in `GRAPH`."""
    return method if method in TRAINED_IMAGE else GRAPH


def trains(training: Training, method: str) -> bool:
    return group(method) in training.trains


def study_training(study: Study, method: str = "gcn") -> Optional[Training]:
    """The `Training` of `TRAININGS` that is the study's own for `method` (the learning rate and schedule of its
    spec, `Study.gcn_spec`), if any."""
    g = study.gcn_spec(method)
    return next((t for t in TRAININGS if math.isclose(t.lr, g.lr) and t.schedule == g.schedule
                 and trains(t, method)), None)


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


_SHARED: dict = {}  # the study, its graphs and frames while `curves` runs, for the workers it forks


def run_spec(study: Study, method: str, training: Training) -> gcn.GCNSpec:
    """The spec a run of `method` trains with: the study's for the method, with `training`'s learning rate,
    schedule and epochs, every epoch run and recorded."""
    return dataclasses.replace(study.gcn_spec(method), patience=training.epochs + 1, select="val_recall",
                               min_epochs=1, lr=training.lr, schedule=training.schedule, epochs=training.epochs)


def run_key(study: Study, job: tuple, families: int = INNER_FAMILIES, inputs: Optional[str] = None) -> str:
    """The key of one run (`curves`' job): what it reads and computes, whatever the other runs. `inputs`: the
    method's `cell.inputs_key`, when the caller holds it."""
    method, threshold, seed, with_test, training = job
    if inputs is None:
        inputs = cell.inputs_key(study, method, SCENARIO if group(method) == GRAPH else "rgb")
    return key_of({"inputs": inputs,
                   "encoder": dataclasses.asdict(run_spec(study, method, training)), "threshold": threshold,
                   "seed": seed, "test": with_test, "inner": [families, INNER_POSITIVES, study.seed],
                   "val": study.gcn.val_settings, "deterministic": study.deterministic,
                   "code": versions.code_version("cells")})


def run_path(study: Study, job: tuple, families: int = INNER_FAMILIES, inputs: Optional[str] = None) -> Path:
    """``runs/<study>/selection/<training>/<method>__t<threshold>__s<seed>__<key>.csv``: one run's epochs."""
    method, threshold, seed, _, training = job
    name = f"{method}__t{paths.threshold_tag(threshold)}__s{seed}__{run_key(study, job, families, inputs)[:16]}.csv"
    return paths.study_dir(study.name) / "selection" / training.name.replace(" ", "_").replace(",", "") / name


def _graph_run(study: Study, method: str, threshold: float, seed: int, spec, with_test: bool, on_epoch_of):
    """One graph encoder trained on the inner split of `SCENARIO`'s graphs; `on_epoch_of(embed, inner, test)`."""
    split, test = _SHARED["split"], (_SHARED["test"] if with_test else [])
    projection = study.projection(SCENARIO)
    train, val, inner, test = ([gcn.encoder_graph(g, threshold, spec, projection) for g in part]
                               for part in (*split, test))
    on_epoch = on_epoch_of(gcn.embed, inner, test, [g.frame for g in test])
    return gcn.train(train, val, spec, seed=seed, threads=1, deterministic=study.deterministic, on_epoch=on_epoch)


def _image_run(study: Study, method: str, seed: int, spec, with_test: bool, on_epoch_of):
    """One learned image encoder trained on the same inner split of the frames (`_SHARED["frames"]`)."""
    train, val, inner = _SHARED["frames"]
    test = _SHARED["test_frames"] if with_test else []
    part = selection.Selection(train, val, [])
    keys = [f.key for f in test]
    rule = training_rule(spec)
    if method == "image_triplet":
        tr, va, inn, te = (baselines.image_tensor(fs) for fs in (train, val, inner, test))
        on_epoch = on_epoch_of(baselines.cnn_embed, inn, te, keys)
        return baselines.train_cnn(tr, [f.setting for f in train], va, [f.setting for f in val], rule=rule, seed=seed,
                                   threads=1, deterministic=study.deterministic, on_epoch=on_epoch)
    trunk = {k: features.load(study, fs) for k, fs in (("train", train), ("val", val), ("inner", inner),
                                                        ("test", test))}
    _, head = features.networks()
    on_epoch = on_epoch_of(pretrained.head_embed, torch.from_numpy(trunk["inner"]), torch.from_numpy(trunk["test"]),
                           keys)
    return pretrained.train_head(head, trunk, part, rule=rule, seed=seed, threads=1, deterministic=study.deterministic,
                                 on_epoch=on_epoch)


def _curve(job) -> list[dict]:
    """Worker: every epoch's history row of one (method, threshold, seed) trained all its epochs with `training`,
    read from its file when an earlier comparison ran it (`run_path`), else trained and written there."""
    method, threshold, seed, with_test, training = job
    study = _SHARED["study"]
    path = run_path(study, job, _SHARED["families"], _SHARED["inputs"][method])
    if path.is_file():
        return pd.read_csv(path).to_dict("records")
    if not with_test:  # the same training recorded with its test curve (the curve never changes the training)
        with_curve = run_path(study, (*job[:3], True, training), _SHARED["families"], _SHARED["inputs"][method])
        if with_curve.is_file():
            return pd.read_csv(with_curve).drop(columns="test_recall@1", errors="ignore").to_dict("records")
    spec = run_spec(study, method, training)
    graph = group(method) == GRAPH
    inner_settings = [g.setting for g in (_SHARED["split"][2] if graph else _SHARED["frames"][2])]
    test_settings = [g.setting for g in (_SHARED["test"] if graph else _SHARED["test_frames"])]

    def on_epoch_of(embed, inner, test, test_keys):
        def on_epoch(model):
            row = {"inner_recall@1": test_like_recall(embed(model, inner), inner_settings, seed=study.seed)}
            if len(test):  # the study's own cell metric, for the figure of training.md only: no rule reads it
                result = evaluate.evaluate_protocols(embed(model, test), test_keys, test_settings, study.protocol,
                                                     seed)[PAPER]
                row["test_recall@1"] = result.metrics["recall@1"]
            return row
        return on_epoch

    result = (_graph_run(study, method, threshold, seed, spec, with_test, on_epoch_of) if graph
              else _image_run(study, method, seed, spec, with_test, on_epoch_of))
    rows = [{"training": training.name, "method": method, "threshold": threshold, "seed": seed,
             "run_s": round(result.seconds, 1), **row} for row in result.history]
    write_text(path, pd.DataFrame(rows).to_csv(index=False))
    return rows


def curves(study: Study, configs=CONFIGS, seeds: Optional[list[int]] = None, workers: Optional[int] = None,
           trainings=TRAININGS, families: int = INNER_FAMILIES) -> pd.DataFrame:
    """Every epoch of every run of `trainings` x `configs` x `seeds` (default: the study's) on the inner split of
    `SCENARIO` (each training on the configurations it trains, `Training.trains`; graph encoders where the study
    runs them). The study's own test recall@1 is recorded per epoch for the first seeds of each encoder's own
    training (`study_training`)."""
    graphs = scenegraphs.load(study, SCENARIO)
    split = inner_split(graphs, families, study.seed)
    known = set(study.graph_methods()) | (set() if study.graphs_root else set(TRAINED_IMAGE))  # images: rendered only
    seeds = list(seeds or study.seeds)
    jobs = [(m, float(t), int(s), tr == study_training(study, m) and s in seeds[:TEST_CURVE_SEEDS], tr)
            for tr in trainings for m, t in configs if m in known and trains(tr, m) for s in seeds]
    jobs.sort(key=lambda j: group(j[0]) == GRAPH)  # the long runs (the image encoders') first, then the short ones
    inputs = {m: cell.inputs_key(study, m, SCENARIO if group(m) == GRAPH else "rgb") for m in {j[0] for j in jobs}}
    shared = dict(study=study, split=split, test=graphs["test"], families=families, inputs=inputs)
    if any(group(j[0]) != GRAPH for j in jobs):
        sel = selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings)
        shared.update(frames=inner_split({"train": sel.train, "val": sel.val}, families, study.seed),
                      test_frames=sel.test)
        if any(j[0] in methods.IMAGENET for j in jobs):
            features.load(study, sel.test)  # the features file read once, here, for every forked worker
    _SHARED.update(shared)  # (forked workers inherit the graphs and frames, unpickled)
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
    stopper = EarlyStopping(patience=rule.patience, seed=0, model=nn.Identity(), select=rule.select,
                            min_epochs=rule.min_epochs)
    for row in history[history["epoch"] <= rule.epochs].to_dict("records"):
        if stopper.advance(row, nn.Identity()):
            break
    return stopper.best_epoch, len(stopper.history)


def rules_table(curves_df: pd.DataFrame, rules=RULES) -> pd.DataFrame:
    """Per rule and (method, threshold): the inner test recall@1 of the kept models (mean and seed sd, in %), the
    share of runs that keep a model of epoch 1 or 2, and the mean epochs run; and the rule's row over each group of
    encoders (`group`; ``method`` ``all``: mean of the configurations' means and of their seed sds)."""
    rows = []
    for rule in rules:
        runs = curves_df[curves_df["training"] == rule.training]
        for grp in dict.fromkeys(group(m) for m in runs["method"]):
            per = []
            for (m, t), g in runs[runs["method"].map(group) == grp].groupby(["method", "threshold"], sort=False):
                kept = []
                for _, run in g.groupby("seed", sort=True):
                    run = run.sort_values("epoch")
                    epoch, ran = replay(run, rule)
                    kept.append((epoch, ran, float(run.loc[run["epoch"] == epoch, "inner_recall@1"].iloc[0])))
                epochs, ran, recall = (np.array(v, float) for v in zip(*kept))
                per.append((rule.name, grp, m, t, 100 * recall.mean(),
                            100 * recall.std(ddof=1) if len(recall) > 1 else 0.0, float((epochs <= 2).mean()),
                            ran.mean(), len(recall)))
            rows += per
            p = pd.DataFrame(per)
            rows.append((rule.name, grp, "all", math.nan, p[4].mean(), p[5].mean(), p[6].mean(), p[7].mean(),
                         int(p[8].sum())))
    return pd.DataFrame(rows, columns=["rule", "group", "method", "threshold", "inner_recall@1", "seed_sd",
                                       "kept_epoch_le2", "epochs_run", "runs"])


def best_possible(curves_df: pd.DataFrame) -> pd.DataFrame:
    """Per (method, threshold): the inner test recall@1 of the best epoch of each run (an oracle no rule can reach:
    it reads the inner test), mean over seeds, in %."""
    best = curves_df.groupby(["method", "threshold", "seed"], sort=False)["inner_recall@1"].max()  # any training
    return (100 * best.groupby(["method", "threshold"], sort=False).mean()).rename("oracle").reset_index()


def _threshold(t: float) -> str:
    return "∞" if math.isinf(t) else f"{t:g}"


def spec_rule(spec) -> Rule:
    """The rule a spec trains and selects by (its `select`, `min_epochs`, `patience` and `epochs`)."""
    return Rule("study", spec.select, spec.min_epochs, spec.patience, spec.epochs)


def study_rule(study: Study, method: str = "gcn", rules=RULES) -> Optional[Rule]:
    """The rule of `rules` that the study's settings of `method` (`Study.gcn_spec`) train and select by, if any."""
    g, own = study.gcn_spec(method), study_training(study, method)
    for r in rules:
        same_stop = r.select == "last" or (r.min_epochs, r.patience) == (g.min_epochs, g.patience)
        if own and r.training == own.name and r.select == g.select and r.epochs == g.epochs and same_stop:
            return r
    return None


# How a rule is chosen from the table, per group: among the rules that fit the group's budget of epochs (make
# study's time for the graph encoders, which train in every scenario and threshold; the image encoders run in make
# ablations, one cell per seed, and may train every epoch compared), those whose inner recall@1 is within `LEVEL`
# points of the best; of these the one with the lowest seed sd (a seed should not decide a cell). A rule within
# `LEVEL` of both (recall and seed sd) is level with it: which of them is lower moves from one CPU to another, so a
# study that trains by one of them keeps it rather than re-make every figure for a difference within the noise.
BUDGET = {GRAPH: 20}     # at most this many epochs a run; a group not named: every rule
LEVEL = 1.0              # points of inner recall@1, and of seed sd


def recommend(table: pd.DataFrame, grp: str) -> list[str]:
    """The rules `BUDGET` and `LEVEL` choose for group `grp` from `rules_table`'s rows: the chosen one first, then
    those level with it; [] when no rule fits the budget."""
    rows = table[(table["group"] == grp) & (table["method"] == "all")]
    rows = rows[rows["epochs_run"] <= BUDGET.get(grp, math.inf)]
    if rows.empty:
        return []
    level = rows[rows["inner_recall@1"] >= rows["inner_recall@1"].max() - LEVEL]
    level = level.sort_values(["seed_sd", "inner_recall@1"], ascending=[True, False])
    return [str(r) for r in level.loc[level["seed_sd"] <= level["seed_sd"].iloc[0] + LEVEL, "rule"]]


def start_recall(study: Study, families: int = INNER_FAMILIES) -> float:
    """The inner test recall@1 of `imagenet_triplet` before any training (the encoder starts as `imagenet_gem`)."""
    sel = selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings)
    inner = inner_split({"train": sel.train, "val": sel.val}, families, study.seed)[2]
    _, head = features.networks()
    emb = pretrained.head_embed(pretrained.HeadEncoder(head, pretrained.TRIPLET_OUT),
                                torch.from_numpy(features.load(study, inner)))
    return test_like_recall(emb, [f.setting for f in inner], seed=study.seed)


def _group_lines(table: pd.DataFrame, oracle: pd.DataFrame, grp: str, chosen: Optional[Rule],
                 start: Optional[float] = None) -> list[str]:
    """The tables of one group: every rule over the group's runs, then (several configurations) per configuration
    with the oracle beside, then the rule `recommend` chooses and the study's rule; `start`: the inner recall@1
    before training (%), where the encoder starts trained."""
    sub = table[table["group"] == grp]
    title = "The graph encoders" if grp == GRAPH else f"`{grp}`"
    lines = ["", f"**{title}**", "", "| rule | inner recall@1 | seed sd | epoch 1-2 | epochs run |",
             "|---|---:|---:|---:|---:|"]
    for _, r in sub[sub["method"] == "all"].iterrows():
        lines.append(f"| {r['rule']} | {r['inner_recall@1']:.1f} | {r['seed_sd']:.1f} | {r['kept_epoch_le2']:.2f} | "
                     f"{r['epochs_run']:.1f} |")
    configs = sub[sub["method"] != "all"][["method", "threshold"]].drop_duplicates()
    orc = {(m, t): v for m, t, v in oracle.itertuples(index=False)}
    if len(configs) > 1:
        lines += ["", "Per encoder (inner recall@1, mean ± seed sd; oracle: the best epoch of each run, read off the "
                  "inner test):", "",
                  "| rule | " + " | ".join(f"`{m}` {_threshold(t)}" for m, t in configs.itertuples(index=False)) + " |",
                  "|---|" + "---:|" * len(configs)]
        for name, g in sub[sub["method"] != "all"].groupby("rule", sort=False):
            cells = [f"{r['inner_recall@1']:.1f} ± {r['seed_sd']:.1f}" for _, r in g.iterrows()]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        lines.append("| oracle | " + " | ".join(f"{orc[(m, t)]:.1f}" for m, t in configs.itertuples(index=False))
                     + " |")
    else:
        lines += ["", "Oracle (the best epoch of each run, read off the inner test): "
                  + ", ".join(f"{orc[(m, t)]:.1f}" for m, t in configs.itertuples(index=False))
                  + ("" if start is None else f"; before any training (the encoder as it starts): {start:.1f}") + "."]
    budget, picked = BUDGET.get(grp), recommend(table, grp)
    lines += ["", f"Chosen by the criterion ({f'at most {budget} epochs a run, ' if budget else ''}inner recall@1 "
                  f"within {LEVEL:g} point of the best, then the lowest seed sd; level: within {LEVEL:g} point of it "
                  f"in both): **{picked[0] if picked else 'none'}**"
              + (" (level with it: " + "; ".join(picked[1:]) + ")" if len(picked) > 1 else "") + ". "
              + (f"The study trains {'them' if grp == GRAPH else 'it'} by the rule **{chosen.name}**"
                 + ("" if chosen.name in picked else ", not one of these") + "."
                 if chosen is not None else "The study's training is none of the rules compared.")]
    return lines


def markdown(table: pd.DataFrame, oracle: pd.DataFrame, study_name: str, cpu_seconds: float,
             chosen: Optional[dict] = None, start: Optional[dict] = None, families: int = INNER_FAMILIES,
             volumes: bool = False) -> str:
    """selection.md: per group of encoders (`group`) every rule over its runs, then per configuration, the oracle
    beside; `chosen`: {group: the study's rule}; `start`: {group: inner recall@1 (%) before training}.
    `cpu_seconds`: the runs' training, summed; `families`: held out as the inner test (`volumes`: volumes of fold
    0's training side, else families of two settings)."""
    held = (f"{families} volumes of fold 0's training side held out as an inner test (every setting of each; the "
            f"fold's test volumes are never read)" if volumes else
            f"{families} training families held out as an inner test (both settings each)")
    groups = set(table["group"])  # the trainings as far as they trained the encoders compared here
    trainings = "; ".join(f"{t.name} ({t.schedule}, {t.epochs} epochs: "
                          + ", ".join("graph encoders" if x == GRAPH else f"`{x}`" for x in t.trains if x in groups)
                          + ")" for t in TRAININGS if groups & set(t.trains))
    lines = [f"**Model selection, measured on the training split of `{study_name}`** (`monolib bench selection`, "
             f"{cpu_seconds / 60:.0f} CPU-minutes of training, one thread a run). {held}, queried as the paper's "
             f"protocol queries its test "
             f"({INNER_POSITIVES} positives per setting, the other frames query, every frame of the other settings a "
             f"candidate); the study's validation settings as they are; each encoder trained all its epochs once per "
             f"seed and training ({trainings}), each rule replayed on the recorded epochs of its training (rules "
             f"without a learning rate: 0.001). Inner recall@1 in %; seed sd: standard deviation over seeds, mean "
             f"over configurations; epoch 1-2: share of runs whose kept model is from epoch 1 or 2."]
    for grp in sorted(dict.fromkeys(table["group"]), key=lambda g: g != GRAPH):  # the graph encoders first
        lines += _group_lines(table, oracle, grp, (chosen or {}).get(grp), (start or {}).get(grp))
    return "\n".join(lines) + "\n"


def inner_families(study: Study) -> int:
    """How many families the inner test holds: `INNER_FAMILIES` pairs of the mini-Hypersim; with folds by volume
    (`protocol.split: volumes`), as many volumes as fold 0's own test holds, so that the inner test is a fold's
    size."""
    if study.protocol.split != "volumes":
        return INNER_FAMILIES
    return len({family(g.setting) for g in scenegraphs.load(study.at_fold(0), SCENARIO)["test"]})


def split_study(study: Study) -> Study:
    """The study whose training split the comparison holds out from: itself, or with folds by volume its fold 0
    (its training volumes, never the fold's test)."""
    return study.at_fold(0) if study.protocol.split == "volumes" else study


def write(study: Study, out: Path, seeds: Optional[list[int]] = None) -> dict[str, Path]:
    """Run the comparison on `study`'s training split (with folds by volume: fold 0's; the runs not yet in
    ``runs/<study>/selection/``) and write its files into `out`."""
    study = split_study(study)
    families = inner_families(study)
    df = curves(study, seeds=seeds, families=families)
    table = rules_table(df)
    out = Path(out)
    files = {"md": out / "selection.md", "rules": out / "selection_rules.csv", "curves": out / "selection_curves.csv"}
    cpu = float(df.groupby(["training", "method", "threshold", "seed"])["run_s"].first().sum())
    chosen = {group(m): study_rule(study, m) for m in ("gcn", *TRAINED_IMAGE)}
    start = {"imagenet_triplet": 100 * start_recall(study)} if "imagenet_triplet" in set(df["method"]) else {}
    write_text(files["curves"], df.drop(columns="run_s").to_csv(index=False))
    write_text(files["rules"], table.to_csv(index=False))
    write_text(files["md"], markdown(table, best_possible(df), study.name, cpu, chosen, start, families,
                                     study.protocol.split == "volumes"))
    return files
