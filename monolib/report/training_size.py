"""How much training size decides, on both legs: the committed results of each leg's studies at growing training
sizes (`CURVE`), read from their ``intervals.csv`` (each written by its study's report from its cells).

- ``training_size.{md,csv}``: recall@1 (scenario 1, ground truth, ``paper`` protocol; mean [95 % interval]) of the
  rows of `ROWS` (the paper's GCN at no edges, its best threshold, its dip and every pair joined; ``ours`` and
  ``layout`` where the studies run them) at each training size of each leg, the paper's number beside;
- ``training_size.png``: the same, one panel per leg;
- ``reproduces.md``: the paper's GCN at every threshold beside the paper's column, on the real folds and on the
  mini-Hypersim at the smallest and the largest training size of each leg, with the comparisons of the real leg's
  largest study (`monolib.report.folds.reproduces_markdown`): the README's answer to "does it reproduce".

A study whose ``intervals.csv`` is missing (not run yet) is left out of every table and said so in the text, so
that the report can be written after any one of the studies.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import pandas as pd

from monolib import io, paths
from monolib.params import load_study
from monolib.report import bootstrap, folds, tables
from monolib.report.figures import new_figure

log = logging.getLogger(__name__)

# each leg's studies, from the smallest training size to the largest
CURVE = {"mini-Hypersim": ("quick", "quick_96x40", "paper_scale"),
         "real folds": ("real", "real_96x40", "real_full")}
ROWS = (("gcn", 0.0), ("gcn", 1.0), ("gcn", 5.0), ("gcn", math.inf), ("ours", 0.0), ("layout", math.inf))
COLUMNS = ["leg", "study", "size", "method", "threshold", "mean", "ci_lo", "ci_hi", "n_seeds", "paper"]


def study_rows(study_name: str) -> pd.DataFrame:
    """Scenario-1 recall@1 rows of a committed study's ``intervals.csv`` (``paper`` protocol; thresholds as floats);
    empty when the study has not been run."""
    path = paths.figures_dir(study_name) / "intervals.csv"
    if not path.is_file():
        log.warning("training size: %s not found (run the study first): left out", path)
        return pd.DataFrame(columns=bootstrap.INTERVAL_COLUMNS)
    return folds.recall1(pd.read_csv(path))


def curve() -> pd.DataFrame:
    """One row per leg, study and row of `ROWS` that the study holds: its training size (``48 x 20``: training
    settings x frames of each), mean, interval, seeds and the paper's number (the GCN's, where the paper has one)."""
    paper = folds.paper_recall1()
    out = []
    for leg, studies in CURVE.items():
        for name in studies:
            rows = study_rows(name)
            if rows.empty:
                continue
            size = folds.size_label(load_study(name, check_files=False))
            for method, t in ROWS:
                r = rows[(rows["method"] == method) & (rows["threshold"] == t)]
                if r.empty:
                    continue
                r = r.iloc[0]
                out.append({"leg": leg, "study": name, "size": size, "method": method, "threshold": t,
                            "mean": float(r["mean"]), "ci_lo": float(r["ci_lo"]), "ci_hi": float(r["ci_hi"]),
                            "n_seeds": int(r["n_seeds"]), "paper": paper.get(t) if method == "gcn" else None})
    return pd.DataFrame(out, columns=COLUMNS)


def markdown(t: pd.DataFrame) -> str:
    """``training_size.md``: one table per leg, a column per training size."""
    lines = ["# Training size", "",
             "Recall@1 (%), ground truth (scenario 1), `paper` protocol, mean [95 % bootstrap interval] at each "
             "training size (training settings x frames of each, the validation settings among them). The "
             "mini-Hypersim's studies share quick's test split (16 settings; `dataset.base_train_settings`), each "
             "larger training split holding quick's 48 training settings (with more frames each) and further "
             "families; the real leg's are 5 folds by volume of the published graphs' development set, each size a "
             "seeded subsample of each fold's training settings (`all`: every one). Studies: " + "; ".join(
                 f"{leg}: " + ", ".join(f"`{s}`" for s in studies) for leg, studies in CURVE.items()) + ".", ""]
    rules = []
    for name in (s for studies in CURVE.values() for s in studies):
        g = load_study(name, check_files=False).gcn
        rules.append(f"`{name}` {g.epochs} at {g.lr:g}")
    lines += ["Training rule of each study (epochs at its learning rate, the model of the last epoch; each study's "
              "file says why): " + ", ".join(rules) + ".", ""]
    missing = [s for studies in CURVE.values() for s in studies if s not in set(t["study"])]
    if missing:
        lines += ["Not run yet (left out): " + ", ".join(f"`{s}`" for s in missing) + ".", ""]
    for leg, g in t.groupby("leg", sort=False):
        sizes = list(dict.fromkeys(g["size"]))
        lines += [f"## {leg}", "", "| method | threshold (m) | " + " | ".join(sizes)
                  + f" | {sizes[-1]} against {sizes[0]} | paper |", "| --- | --- |" + " ---: |" * (len(sizes) + 2)]
        for (method, thr), rows in g.groupby(["method", "threshold"], sort=False):
            by_size = {r.size: folds.mean_ci(r.mean, r.ci_lo, r.ci_hi) for r in rows.itertuples()}
            paper = rows["paper"].iloc[0]
            lines.append(f"| {method} | {tables.threshold_label(thr)} | "
                         + " | ".join(by_size.get(s, "") for s in sizes) + f" | {change(rows, sizes)} | "
                         + f"{'' if paper is None or paper != paper else format(paper, '.1f')} |")
        lines += ["", f"{sizes[-1]} against {sizes[0]}: the difference of the means; *apart* when the two intervals "
                  "do not overlap (a conservative test: the intervals are each study's own, not a paired bootstrap "
                  "of the difference), *overlapping* otherwise.", ""]
    return "\n".join(lines)


def change(rows: pd.DataFrame, sizes: list[str]) -> str:
    """The largest size's mean minus the smallest's, and whether their intervals are apart: '+9.8, apart'."""
    ends = [rows[rows["size"] == s] for s in (sizes[0], sizes[-1])]
    if len(sizes) < 2 or any(e.empty for e in ends):
        return ""
    a, b = ends[0].iloc[0], ends[1].iloc[0]
    apart = b["ci_lo"] > a["ci_hi"] or b["ci_hi"] < a["ci_lo"]
    return f"{tables.signed(b['mean'] - a['mean'])}, {'apart' if apart else 'overlapping'}"


def plot(t: pd.DataFrame, path: Path) -> Path:
    """``training_size.png``: recall@1 against training size, one panel per leg, one line per row of `ROWS` with
    its interval; the paper's number of each GCN threshold as a dotted line of the same colour."""
    legs = list(dict.fromkeys(t["leg"]))
    fig = new_figure(figsize=(5.2 * max(1, len(legs)), 3.8))
    axes = fig.subplots(1, max(1, len(legs)), squeeze=False)[0]
    for ax, leg in zip(axes, legs):
        g = t[t["leg"] == leg]
        sizes = list(dict.fromkeys(g["size"]))
        groups = list(g.groupby(["method", "threshold"], sort=False))
        for i, ((method, thr), rows) in enumerate(groups):
            x = [sizes.index(s) + 0.03 * (i - (len(groups) - 1) / 2) for s in rows["size"]]  # bars side by side
            colour = f"C{i}"
            ax.errorbar(x, rows["mean"], yerr=[rows["mean"] - rows["ci_lo"], rows["ci_hi"] - rows["mean"]],
                        color=colour, marker="o", capsize=3, label=f"{method}, {tables.threshold_label(thr)}")
            paper = rows["paper"].iloc[0]
            if paper is not None and paper == paper:
                ax.axhline(paper, color=colour, linestyle=":", linewidth=1)
        ax.set_xticks(range(len(sizes)), sizes)
        ax.set_xlabel("training settings x frames")
        ax.set_ylabel("recall@1 (%)")
        ax.set_title(leg)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    fig.suptitle("Training size (dotted: the paper's GCN at that threshold)", fontsize=10)
    return io.save_figure(fig, path)


def reproduces(real_study: str = CURVE["real folds"][-1]) -> str | None:
    """``reproduces.md`` from the committed files: the real leg's smallest and largest studies, the mini-Hypersim's
    smallest and largest, and the comparisons of `real_study` (its ``real_vs_synth.csv``); None while any of them
    is missing."""
    real_ends = [CURVE["real folds"][0], CURVE["real folds"][-1]]
    mini_ends = [CURVE["mini-Hypersim"][0], CURVE["mini-Hypersim"][-1]]
    rvs_path = paths.figures_dir(real_study) / "real_vs_synth.csv"
    ivs = {name: paths.figures_dir(name) / "intervals.csv" for name in real_ends + mini_ends}
    if not rvs_path.is_file() or not all(p.is_file() for p in ivs.values()):
        return None
    label = lambda name: folds.size_label(load_study(name, check_files=False))  # noqa: E731
    sizes = [(label(n), pd.read_csv(ivs[n])) for n in real_ends]
    minis = [(label(n), folds.recall1(pd.read_csv(ivs[n]))) for n in mini_ends]
    best = folds.best_thresholds(sizes[-1][1], minis[0][1])
    text = folds.reproduces_markdown(load_study(real_study, check_files=False), pd.read_csv(rvs_path), best, sizes,
                                     minis)
    columns = [(f"real folds, {label}", folds.recall1(x)) for label, x in sizes]
    return text + "\n" + paper_inside(columns + [(f"mini-Hypersim, {label}", x) for label, x in minis])


def paper_inside(columns: list[tuple[str, pd.DataFrame]]) -> str:
    """One generated line per column (``(name, scenario-1 recall@1 rows)``): at how many of the paper's thresholds
    the interval of the paper's GCN holds the paper's number, and at which the paper's number lies above or below."""
    paper = folds.paper_recall1()
    lines = ["Where the paper's number lies against each interval of the paper's GCN above:", ""]
    for name, x in columns:
        g = x[x["method"] == "gcn"]
        side: dict[str, list[str]] = {"inside": [], "above": [], "below": []}
        for t, value in sorted(paper.items()):
            r = g[g["threshold"] == t]
            if r.empty:
                continue
            lo, hi = r["ci_lo"].iloc[0], r["ci_hi"].iloc[0]
            at = tables.threshold_label(t) + ("" if math.isinf(t) else " m")
            side["above" if value > hi else "below" if value < lo else "inside"].append(at)
        total = sum(len(v) for v in side.values())
        lines.append(f"- {name}: inside the interval at {len(side['inside'])} of {total} thresholds"
                     + "".join(f"; the paper's {k} it at {', '.join(side[k])}" for k in ("above", "below") if side[k])
                     + ".")
    return "\n".join(lines) + "\n"


def write(out: Path = paths.FIGURES) -> dict[str, Path]:
    """Write ``training_size.{md,csv,png}`` and ``reproduces.md`` (when its studies are all there) into `out`."""
    t = curve()
    written = {"training_size_csv": out / "training_size.csv", "training_size": out / "training_size.md"}
    io.write_text(written["training_size_csv"], tables.csv_text(t))
    io.write_text(written["training_size"], markdown(t))
    if len(t):
        written["training_size_png"] = plot(t, out / "training_size.png")
    text = reproduces()
    if text is not None:
        io.write_text(out / "reproduces.md", text)
        written["reproduces"] = out / "reproduces.md"
    return written
