"""How the trained encoders' training ended: ``training.md`` / ``training.csv`` and ``training_curves.png``.

For every trained method (graph encoders, `image_triplet`, `imagenet_triplet`: the cells whose record holds a
``best_epoch``), per scenario and threshold: the epochs run and the epoch of the kept model (median, min, max over
seeds), the share of seeds whose kept model is from epoch 1 or 2, and the seed standard deviation of recall@1 on
the ``paper`` protocol; per method and scenario the same over all its thresholds. A cell copied from a smaller
threshold with identical graphs (``same_graphs_as``) is the same training and counts once, at that threshold; a
cell copied from another scenario with the same encoder inputs (``same_inputs_as``) is shown in its own scenario.

``training_curves.png`` draws, when `monolib bench selection` has written ``selection_curves.csv`` into the same
folder, validation recall@1 and mAP, the inner test's recall@1 (training settings held out) and the study's test
recall@1 against the epoch for a few runs, with the epoch each run's selection keeps.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Collection, Optional

import pandas as pd

from monolib import io
from monolib.params import PAPER
from monolib.report.results import cell_files, cell_metrics, natural_key, threshold_value
from monolib.params import TRAINED_IMAGE_METHODS
from monolib.retrieval.model_selection import replay, spec_rule, study_training

EARLY = 2  # a kept model from epoch 1 or 2: trained for hardly anything
COLUMNS = ["method", "scenario", "threshold", "seeds", "epochs_run_median", "epochs_run_min", "epochs_run_max",
           "best_epoch_median", "best_epoch_min", "best_epoch_max", "kept_early", "recall@1_mean", "recall@1_seed_sd",
           "recall@1_se"]
# What a trained encoder is held to: the seed sd of recall@1 of these methods on these scenarios, the share of a
# method's runs kept from epoch 1 or 2, and the standard error of a cell's mean over its seeds (sd / sqrt(seeds)).
TARGET_METHODS, TARGET_SCENARIOS = ("gcn", "ours", "layout"), ("s1", "s2")
TARGET_SD, TARGET_EARLY, TARGET_SE = 6.0, 0.10, 3.0


def training_cells(study_name: str, grid: Optional[Collection[str]] = None) -> pd.DataFrame:
    """One row per trained cell: method, scenario, threshold, seed, best_epoch, epochs_run, recall@1 (paper, %)."""
    rows = []
    for f in cell_files(study_name, grid):
        cell = io.read_json(f)
        if cell.get("best_epoch") is None or cell.get("same_graphs_as"):
            continue
        rows.append((cell["method"], cell["scenario"], threshold_value(cell["threshold"]), int(cell["seed"]),
                     int(cell["best_epoch"]), int(cell["epochs_run"]), cell_metrics(cell)[PAPER]["recall@1"]))
    return pd.DataFrame(rows, columns=["method", "scenario", "threshold", "seed", "best_epoch", "epochs_run",
                                       "recall@1"])


def _summary(g: pd.DataFrame) -> tuple:
    sd = float(g["recall@1"].std(ddof=1)) if len(g) > 1 else math.nan
    return (len(g), float(g["epochs_run"].median()), int(g["epochs_run"].min()), int(g["epochs_run"].max()),
            float(g["best_epoch"].median()), int(g["best_epoch"].min()), int(g["best_epoch"].max()),
            float((g["best_epoch"] <= EARLY).mean()), float(g["recall@1"].mean()), sd, sd / math.sqrt(len(g)))


def training_table(cells: pd.DataFrame) -> pd.DataFrame:
    """Per (method, scenario, threshold) `_summary` of its seeds, then per (method, scenario) over every threshold
    (``threshold`` NaN; its seed sd: the largest of its thresholds')."""
    rows = []
    for (m, sc), g in cells.groupby(["method", "scenario"], sort=False):
        per = [(m, sc, t, *_summary(h)) for t, h in g.groupby("threshold", sort=True)]
        rows += per
        if len(per) > 1:
            whole = list(_summary(g))
            whole[-2] = max((r[-2] for r in per if not math.isnan(r[-2])), default=math.nan)
            whole[-1] = max((r[-1] for r in per if not math.isnan(r[-1])), default=math.nan)
            rows.append((m, sc, math.nan, *whole))
    out = pd.DataFrame(rows, columns=COLUMNS)
    order = sorted(set(out["method"]), key=natural_key)
    out["_m"] = out["method"].map({m: i for i, m in enumerate(order)})
    scenarios = sorted(set(out["scenario"]), key=natural_key)
    out["_s"] = out["scenario"].map({sc: i for i, sc in enumerate(scenarios)})
    return out.sort_values(["_m", "_s"], kind="mergesort").drop(columns=["_m", "_s"]).reset_index(drop=True)


def _t(value: float) -> str:
    if isinstance(value, float) and math.isnan(value):
        return "all"
    return "∞" if math.isinf(value) else f"{value:g}"


def markdown(table: pd.DataFrame, study_name: str, selection: Optional[str] = None) -> str:
    """training.md of `training_table`."""
    lines = [f"**How training ended, `{study_name}`** (every trained cell; a cell copied from a smaller threshold "
             f"with identical graphs counts once; a cell copied from another scenario whose encoder reads the same "
             f"inputs is shown in its own scenario's rows). Epochs run and the kept model's epoch: median [min, max] "
             f"over seeds; epoch 1-2: share of seeds whose kept model is from epoch 1 or 2; recall@1 on `paper`, mean "
             f"and seed standard deviation (%). Rows `all`: every threshold of the method and scenario (seed sd: the "
             f"largest)." + (f" Selection: {selection}." if selection else ""), "",
             "| method | scenario | threshold (m) | seeds | epochs run | kept epoch | epoch 1-2 | recall@1 | seed sd | "
             "SE |", "|---|---|---|---:|---|---|---:|---:|---:|---:|"]
    for _, r in table.iterrows():
        lines.append(f"| `{r['method']}` | {r['scenario']} | {_t(r['threshold'])} | {r['seeds']} | "
                     f"{r['epochs_run_median']:g} [{r['epochs_run_min']}, {r['epochs_run_max']}] | "
                     f"{r['best_epoch_median']:g} [{r['best_epoch_min']}, {r['best_epoch_max']}] | "
                     f"{r['kept_early']:.2f} | {r['recall@1_mean']:.1f} | "
                     + " | ".join("–" if math.isnan(r[k]) else f"{r[k]:.1f}"
                                  for k in ("recall@1_seed_sd", "recall@1_se"))
                     + " |")
    return "\n".join(lines + [""] + checks(table)) + "\n"


def seeds_needed(sd: float, se: float = TARGET_SE) -> int:
    """The seeds a cell needs for a standard error of its mean of at most `se` at a seed sd of `sd`."""
    return max(2, math.ceil((sd / se) ** 2 - 1e-9))


def checks(table: pd.DataFrame) -> list[str]:
    """The targets a trained encoder is held to, each with what this study measured: the seed sd of
    `TARGET_METHODS` on `TARGET_SCENARIOS` (at most `TARGET_SD`), the share of each method's runs kept from epoch 1
    or 2 (at most `TARGET_EARLY`), and each cell mean's standard error (at most `TARGET_SE`)."""
    cells = table[table["threshold"].notna()]
    target = cells[cells["method"].isin(TARGET_METHODS) & cells["scenario"].isin(TARGET_SCENARIOS)]
    over = target[target["recall@1_seed_sd"] > TARGET_SD]
    lines = [f"**Targets.** Seed sd of recall@1 at most {TARGET_SD:g} in every cell of "
             + ", ".join(f"`{m}`" for m in TARGET_METHODS) + " on " + " and ".join(TARGET_SCENARIOS) + ": "
             + (f"{len(target) - len(over)} of {len(target)} cells" if len(target) else "no such cell")
             + ("" if over.empty else " (over: " + ", ".join(
                 f"`{r['method']}` {r['scenario']} {_t(r['threshold'])} m {r['recall@1_seed_sd']:.1f}"
                 for _, r in over.iterrows()) + ")") + "."]
    early = []
    for m, g in cells.groupby("method", sort=False):
        share = float((g["kept_early"] * g["seeds"]).sum() / g["seeds"].sum())
        early.append(f"`{m}` {share:.2f}" + ("" if share <= TARGET_EARLY else " (over)"))
    lines.append(f"Share of runs whose kept model is from epoch 1 or 2 (at most {TARGET_EARLY:.2f}): "
                 + ", ".join(early) + ".")
    se = cells["recall@1_se"].dropna()
    over = cells.loc[se[se > TARGET_SE].index]
    lines.append(f"Standard error of a cell's mean over its seeds at most {TARGET_SE:g}: "
                 f"{int((se <= TARGET_SE).sum())} of {len(se)} cells" + ("" if over.empty else " (over: " + "; ".join(
                     f"`{r['method']}` {r['scenario']} {_t(r['threshold'])} m, {r['recall@1_se']:.1f} with "
                     f"{r['seeds']} seeds, {seeds_needed(r['recall@1_seed_sd'])} at its spread"
                     for _, r in over.iterrows()) + "; more seeds for a cell: the study key `more_seeds`)") + ".")
    return lines


CURVE_RUNS = (("gcn", 0.0, 0), ("gcn", 1.0, 0), ("gcn", 1.0, 1), ("gcn", 5.0, 0), ("ours", 0.0, 0),
              ("layout", math.inf, 0))


def fig_curves(curves: pd.DataFrame, path: Path, kept: dict) -> Optional[Path]:
    """training_curves.png: per run of `CURVE_RUNS` found in `curves`, the validation and test scores against the
    epoch, the kept epoch (`kept[(method, threshold, seed)]`) marked."""
    import matplotlib.pyplot as plt

    runs = [r for r in CURVE_RUNS if ((curves["method"] == r[0]) & (curves["threshold"] == r[1])
                                      & (curves["seed"] == r[2])).any()]
    if not runs:
        return None
    fig, axes = plt.subplots(1, len(runs), figsize=(3.2 * len(runs), 3.0), sharey=True, squeeze=False)
    for ax, (m, t, s) in zip(axes[0], runs):
        run = curves[(curves["method"] == m) & (curves["threshold"] == t) & (curves["seed"] == s)].sort_values("epoch")
        for col, label, scale in (("val_recall@1", "val recall@1", 100), ("val_map", "val mAP", 100),
                                  ("inner_recall@1", "inner test recall@1", 100),
                                  ("test_recall@1", "test recall@1", 1)):
            if col in run and run[col].notna().any():  # (the history's shares as %, as the test metric is)
                ax.plot(run["epoch"], scale * run[col], label=label, lw=1.2)
        if (m, t, s) in kept:
            ax.axvline(kept[(m, t, s)], color="k", ls=":", lw=1)
        ax.set_title(f"{m}, {_t(t)} m, seed {s}", fontsize=9)
        ax.set_xlabel("epoch")
    axes[0][0].set_ylabel("score (%)")
    axes[0][-1].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    io.save_figure(fig, path)
    plt.close(fig)
    return path


def _training_of(g) -> str:
    """How a spec trains, in its keys: learning rate, schedule, epochs, selection."""
    return (f"lr {g.lr:g}, schedule {g.schedule}, epochs {g.epochs}, select {g.select}"
            + ("" if g.select == "last" else f", min_epochs {g.min_epochs}, patience {g.patience}"))


def write(study_name: str, out: Path, grid: Optional[Collection[str]] = None, study=None) -> dict[str, Path]:
    """training.md, training.csv and (with selection_curves.csv in `out`) training_curves.png; {} without a trained
    cell."""
    cells = training_cells(study_name, grid)
    if cells.empty:
        return {}
    out = Path(out)
    table = training_table(cells)
    selection = None
    if study is not None:
        keys = {"gcn": "gcn", **{m: f"image_training.{m}" for m in TRAINED_IMAGE_METHODS if m in study.methods}}
        selection = "; ".join(f"`{key}`: " + _training_of(study.gcn_spec(m)) for m, key in keys.items()) \
            + " (figures/selection.md: the rules compared)"
    written = {"training_md": out / "training.md", "training_csv": out / "training.csv"}
    io.write_text(written["training_csv"], table.to_csv(index=False, float_format="%.6g", lineterminator="\n"))
    io.write_text(written["training_md"], markdown(table, study_name, selection))
    curves_csv = out / "selection_curves.csv"
    if curves_csv.is_file() and study is not None:
        curves = pd.read_csv(curves_csv)
        own = study_training(study)
        if "training" in curves:  # the runs of the study's own training (none: the figure is left out)
            curves = curves[curves["training"] == (own.name if own else None)]
        rule = spec_rule(study.gcn)
        kept = {(m, float(t), int(s)): replay(run.sort_values("epoch"), rule)[0]
                for (m, t, s), run in curves.groupby(["method", "threshold", "seed"])}
        png = fig_curves(curves, out / "training_curves.png", kept)
        if png is not None:
            written["training_curves"] = png
    return written
