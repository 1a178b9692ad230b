"""The report of a study cross-validated by volume (`protocol.split: volumes`), beside its release-split tables, or
alone for a study of folds only (``protocol.release_split: false``, such as the development set's):

- ``folds_intervals.csv``: per (method, scenario, threshold, metric, k) the mean over folds and seeds and its 95 %
  interval resampling folds, test settings, queries and seeds (`monolib.report.bootstrap.FoldBootstrap`), ``paper``
  protocol; a study of folds only writes it as its ``intervals.csv`` too (what `monolib verify` compares);
- ``folds_table1_recall.{md,csv}``, ``folds_table2_precision.{md,csv}``: Tables 1-2 over the folds, the release
  split in its own column when there is one (its ``intervals.csv``, written by the report before), the paper's
  numbers beside;
- ``folds.md`` / ``folds.csv``: each fold's test volumes and the fidelity statistics of its test graphs (nodes per
  graph, label-set Jaccard, wall colour ratio; `monolib.graphs.fidelity.split_statistics`), so that a reader sees
  why folds differ;
- ``real_vs_synth.{md,csv}``: each scenario-1 comparison the tables make (each graph encoder at each threshold
  against itself without edges; each variant against ``gcn`` at the variant's thresholds), its paired recall@1
  difference with interval on the real folds and on the mini-Hypersim (the committed studies of `SYNTH_STUDIES`:
  their ``edge_penalty.csv`` and ``encoder_ablation.csv``), whether the two agree (the same sign with both
  significant, or neither significant), and each encoder's best threshold on both;
- ``edge_penalty.md`` (``folds_edge_penalty.md`` beside a release split): the rows of an encoder against itself;
- a study of folds only: its claims (``claims.{md,csv}``, over folds), ``reproduces.md`` (the paper's recall@1 per
  threshold beside the real folds at each training size and the mini-Hypersim, and a sentence per comparison of
  the paper), and ``training_size.md`` when it extends another study over folds (the same folds at two sizes).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import pandas as pd

from monolib import io, paths
from monolib.data.protocols import family
from monolib.graphs import fidelity, scenegraphs
from monolib.params import PAPER, Study, load_study
from monolib.report import bootstrap, claims, results, tables
from monolib.retrieval.grid import grid

log = logging.getLogger(__name__)
SCENARIO = "s1"          # the scenario of the published graphs (ground truth): the only one compared
SYNTH_STUDY = "quick"    # the committed mini-Hypersim study read for the synthetic side ...
SYNTH_STUDIES = (SYNTH_STUDY, "direction")  # ... and the one holding the undirected encoder's edge penalty
METRIC = "recall@1"      # what the comparisons with the mini-Hypersim compare (the paper's and the README's number)
FIDELITY_COLUMNS = {"nodes per graph, mean": "nodes / graph", "label-set Jaccard, within settings": "Jaccard within",
                    "label-set Jaccard, across settings": "Jaccard across", "wall colour ratio": "wall colour ratio"}


def fold_query_table(study: Study) -> pd.DataFrame:
    """Per-query values (`monolib.report.results.query_table`, ``paper`` protocol) of every fold's cells, with a
    ``fold`` column; empty when no fold has a finished cell."""
    parts = []
    for fold in [f for f in study.folds() if f is not None]:
        names = {c.name for c in grid(study) if c.fold == fold}
        try:
            qv = results.query_table(study.name, names)
        except FileNotFoundError:
            continue
        parts.append(results.only_protocol(qv, PAPER).assign(fold=fold))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


def mean_ci(mean: float, lo: float, hi: float) -> str:
    return "" if mean != mean else f"{mean:.1f} {tables.fmt_ci(lo, hi)}"


def fold_tables(iv: pd.DataFrame, release: pd.DataFrame, metric: str) -> pd.DataFrame:
    """One of Tables 1-2 over folds: per (method, scenario, threshold, k) the folds' mean and interval, the
    release split's (`release`: its ``intervals.csv`` rows), and the paper's number."""
    paper = results.paper_tables()
    rows = []
    for r in iv[iv["metric"] == metric].itertuples():
        rel = release[(release["method"] == r.method) & (release["scenario"] == r.scenario)
                      & (release["threshold"] == r.threshold) & (release["metric"] == metric) & (release["k"] == r.k)]
        pp = paper[(paper["scenario"] == r.scenario) & (paper["threshold"] == r.threshold)
                   & (paper["metric"] == metric) & (paper["k"] == r.k)] if r.method == "gcn" else paper.iloc[:0]
        rows.append({"method": r.method, "scenario": r.scenario, "threshold": r.threshold, "k": r.k,
                     "folds": r.mean, "folds_lo": r.ci_lo, "folds_hi": r.ci_hi, "n_folds": r.n_folds,
                     "n_seeds": r.n_seeds, "release": rel["mean"].iloc[0] if len(rel) else math.nan,
                     "release_lo": rel["ci_lo"].iloc[0] if len(rel) else math.nan,
                     "release_hi": rel["ci_hi"].iloc[0] if len(rel) else math.nan,
                     "paper": pp["value"].iloc[0] if len(pp) else math.nan})
    return pd.DataFrame(rows)


def tables_markdown(t: pd.DataFrame, metric: str, study: Study) -> str:
    """A fold table as markdown: one row per (method, scenario, threshold), one column pair per k."""
    ks = sorted(t["k"].unique())
    cols = ("folds", "release", "paper") if t["release"].notna().any() else ("folds", "paper")
    head = ["method", "scenario", "threshold"] + [f"{metric}@{k} {c}" for k in ks for c in cols]
    lines = [f"# {metric.capitalize()}@k over {study.protocol.folds} folds by volume ({study.name})", "",
             f"Mean over folds and seeds, 95 % bootstrap interval resampling folds, test settings, queries and seeds "
             f"(paper protocol: {study.protocol.settings} test settings of each fold); "
             + ("`release`: the release's own split (its interval over settings, queries and seeds); "
                if "release" in cols else "")
             + "`paper`: the paper's single-run number.", "",
             "| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for (m, sc, th), g in t.groupby(["method", "scenario", "threshold"], sort=False):
        cells = []
        for k in ks:
            r = g[g["k"] == k]
            r = r.iloc[0] if len(r) else None
            cells += ["" if r is None else mean_ci(r.folds, r.folds_lo, r.folds_hi)]
            if "release" in cols:
                cells += ["" if r is None else mean_ci(r.release, r.release_lo, r.release_hi)]
            cells += ["" if r is None or r.paper != r.paper else f"{r.paper:.1f}"]
        lines.append("| " + " | ".join([m, sc, tables.threshold_label(th)] + cells) + " |")
    return "\n".join(lines) + "\n"


def fold_fidelity(study: Study) -> pd.DataFrame:
    """Per split (the release, then each fold): its test volumes and the fidelity statistics of its test graphs
    of scenario `SCENARIO` (built when missing)."""
    rows = []
    for fold in study.folds():
        at = study.at_fold(fold)
        test = scenegraphs.load(at, SCENARIO)["test"]
        stats = fidelity.split_statistics(test)
        volumes = sorted({family(g.setting) for g in test})
        rows.append({"split": "release" if fold is None else f"fold {fold}", "test volumes": ", ".join(volumes),
                     "test settings": int(stats["settings"]), "test graphs": int(stats["graphs"]),
                     **{short: stats.get(name, math.nan) for name, short in FIDELITY_COLUMNS.items()}})
    return pd.DataFrame(rows)


def fidelity_markdown(t: pd.DataFrame, study: Study) -> str:
    split = "train/ alone: no release split" if study.folds_only else "train/ and test/ together"
    lines = [f"# The folds of {study.name}", "",
             f"The volumes of the published graphs ({split}) dealt into {study.protocol.folds} folds by the study's "
             f"seed ({study.seed}), whole volumes; each fold's test split is the paper protocol's "
             f"{study.protocol.settings} settings of its volumes. Fidelity statistics of each test split's graphs "
             f"(`monolib.graphs.fidelity`): nodes per graph (mean), label-set Jaccard of two frames of one setting "
             f"and of two settings, and the wall colour ratio (sd between settings / within a setting; high: a "
             f"wall's colour alone tells the settings apart).", "",
             "| " + " | ".join(t.columns) + " |", "|" + " --- |" * len(t.columns)]
    for r in t.itertuples(index=False):
        lines.append("| " + " | ".join(f"{v:.2f}" if isinstance(v, float) else str(v) for v in r) + " |")
    return "\n".join(lines) + "\n"


def comparisons(study: Study) -> list[tuple[str, float, str, float]]:
    """The scenario-1 comparisons of the tables, ``(method a, threshold a, method b, threshold b)`` for a - b: each
    graph encoder that runs without edges (threshold 0) at each of its other thresholds against itself at 0 (its edge
    penalty), then each variant at each of its thresholds against ``gcn`` at the same threshold."""
    ts = [float(t) for t in study.thresholds]
    out = []
    for name in ["gcn", *study.variants]:
        own = ts if name == "gcn" else [float(t) for t in (study.variants[name].thresholds or ts)]
        if 0.0 in own:
            out += [(name, t, name, 0.0) for t in own if t != 0]
    for name, v in study.variants.items():
        out += [(name, float(t), "gcn", float(t)) for t in (v.thresholds or ts) if float(t) in ts]
    return out


def synth_figures() -> list[Path]:
    """The committed mini-Hypersim studies' figure folders read for the synthetic side, in order of precedence."""
    return [paths.figures_dir(name) for name in SYNTH_STUDIES]


def _shown(path: Path) -> str:
    """A path as the reports print it: relative to the project root when inside it."""
    return str(path.relative_to(paths.ROOT)) if path.is_relative_to(paths.ROOT) else str(path)


def synth_differences(figure_dirs: list[Path]) -> pd.DataFrame:
    """The committed mini-Hypersim differences of the same comparisons, ``paper`` protocol, scenario 1, recall@1:
    an encoder at t against itself at 0 from each folder's ``edge_penalty.csv``, variants against ``gcn`` from its
    ``encoder_ablation.csv``; the first folder that holds a comparison gives it (`figure_dirs`: absolute). Columns
    ``a, ta, b, tb, metric, k, diff, ci_lo, ci_hi, significant, source``."""
    rows = []
    for figures in figure_dirs:
        if (figures / "edge_penalty.csv").is_file():
            pen = pd.read_csv(figures / "edge_penalty.csv")
            pen = pen[(pen["scenario"] == SCENARIO) & (pen["protocol"] == PAPER)]
            for r in pen.itertuples():
                t = results.threshold_value(r.threshold)
                rows.append((r.method, t, r.method, 0.0, r.metric, r.k, r.diff, r.ci_lo, r.ci_hi, r.significant,
                             _shown(figures / "edge_penalty.csv")))
        if (figures / "encoder_ablation.csv").is_file():
            abl = pd.read_csv(figures / "encoder_ablation.csv")
            abl = abl[(abl["scenario"] == SCENARIO) & (abl["protocol"] == PAPER) & abl["diff_vs_base"].notna()]
            for r in abl.itertuples():
                t = results.threshold_value(r.threshold)
                rows.append((r.method, t, "gcn", t, r.metric, r.k, r.diff_vs_base, r.diff_lo, r.diff_hi,
                             r.significant, _shown(figures / "encoder_ablation.csv")))
    out = pd.DataFrame(rows, columns=["a", "ta", "b", "tb", "metric", "k", "diff", "ci_lo", "ci_hi", "significant",
                                      "source"])
    return out.drop_duplicates(["a", "ta", "b", "tb", "metric", "k"], keep="first").reset_index(drop=True)


def agreement(real: pd.Series, synth: pd.Series | None) -> str:
    """``agree`` (same sign, both significant), ``agree: neither significant``, ``disagree``, or ``no synthetic
    number`` when the committed files do not hold the comparison."""
    if synth is None:
        return "no synthetic number"
    if bool(real.significant) and bool(synth.significant):
        return "agree" if (real["diff"] > 0) == (synth["diff"] > 0) else "disagree: opposite signs"
    if not bool(real.significant) and not bool(synth.significant):
        return "agree: neither significant"
    return "disagree: significant on " + ("real folds only" if bool(real.significant) else "the mini-Hypersim only")


def real_vs_synth(study: Study, qv: pd.DataFrame, fboot: bootstrap.FoldBootstrap,
                  figure_dirs: list[Path]) -> pd.DataFrame:
    """Each comparison of `comparisons` on the real folds (`bootstrap.fold_paired_difference`, recall@1) beside the
    mini-Hypersim's (`synth_differences`), with their agreement."""
    synth = synth_differences(figure_dirs)
    rows = []
    for a, ta, b, tb in comparisons(study):
        ra, rb = bootstrap.rows_of(qv, a, SCENARIO, ta), bootstrap.rows_of(qv, b, SCENARIO, tb)
        if ra.empty or rb.empty:
            continue
        for r in bootstrap.fold_paired_difference(ra, rb, fboot, [METRIC]).itertuples():
            if a != b and r.diff == 0 and r.ci_lo == 0 and r.ci_hi == 0:
                continue  # the same numbers query for query: a variant that differs only where it cannot act
            s = synth[(synth["a"] == a) & (synth["ta"] == ta) & (synth["b"] == b) & (synth["tb"] == tb)
                      & (synth["metric"] == r.metric) & (synth["k"] == r.k)]
            srow = s.iloc[0] if len(s) else None
            rows.append({"a": a, "ta": ta, "b": b, "tb": tb,
                         "comparison": f"{a} at {tables.threshold_label(ta)} - {b} at {tables.threshold_label(tb)}",
                         "metric": f"{r.metric}@{r.k}", "real": r.diff, "real_lo": r.ci_lo, "real_hi": r.ci_hi,
                         "real_significant": r.significant, "n_folds": r.n_folds,
                         "synth": math.nan if srow is None else srow["diff"],
                         "synth_lo": math.nan if srow is None else srow.ci_lo,
                         "synth_hi": math.nan if srow is None else srow.ci_hi,
                         "synth_significant": None if srow is None else bool(srow.significant),
                         "synth_source": "" if srow is None else srow.source,
                         "agreement": agreement(pd.Series({"diff": r.diff, "significant": r.significant}), srow)})
    return pd.DataFrame(rows)


def real_vs_synth_markdown(t: pd.DataFrame, study: Study, best: pd.DataFrame) -> str:
    sources = sorted(set(t["synth_source"]) - {""}) if len(t) else []
    lines = [f"# Real folds against the mini-Hypersim ({study.name})", "",
             f"Each scenario-1 comparison of the tables (paper protocol, {METRIC}): the paired difference a - b in "
             f"points, with its 95 % bootstrap interval, on the real folds ({study.protocol.folds} folds by volume of "
             f"the published graphs; resampling folds, settings, queries and seeds) and on the mini-Hypersim (the "
             f"committed studies' {', '.join(f'`{x}`' for x in sources) or 'figures'}). They agree when the two have "
             f"the same sign and both intervals exclude 0, or when neither does.", "",
             "| comparison | real folds | mini-Hypersim | agreement |", "| --- | --- | --- | --- |"]
    for r in t.itertuples():
        real = f"{tables.signed(r.real)} {tables.fmt_ci(r.real_lo, r.real_hi)}"
        synth = "" if r.synth != r.synth else f"{tables.signed(r.synth)} {tables.fmt_ci(r.synth_lo, r.synth_hi)}"
        lines.append(f"| {r.comparison} | {real} | {synth} | {r.agreement} |")
    counts = t["agreement"].value_counts() if len(t) else pd.Series(dtype=int)
    lines += ["", "; ".join(f"{n} {name}" for name, n in counts.items()) or "no comparison with cells yet"]
    if len(best):
        lines += ["", f"Best threshold of each encoder ({METRIC}, mean):", "",
                  "| encoder | real folds | mini-Hypersim |", "| --- | --- | --- |"]
        for r in best.itertuples():
            synth = "" if r.synth_threshold != r.synth_threshold else \
                f"{tables.threshold_label(r.synth_threshold)} ({r.synth_mean:.1f})"
            lines.append(f"| {r.method} | {tables.threshold_label(r.real_threshold)} ({r.real_mean:.1f}) | {synth} |")
    return "\n".join(lines) + "\n"


def paper_recall1() -> dict[float, float]:
    """The paper's recall@1 of its GCN on scenario 1, by threshold (Table 1)."""
    paper = results.paper_tables()
    paper = paper[(paper["scenario"] == SCENARIO) & (paper["metric"] == "recall") & (paper["k"] == 1)]
    return dict(zip(paper["threshold"], paper["value"]))


def recall1(iv: pd.DataFrame) -> pd.DataFrame:
    """The scenario-1 recall@1 rows of an intervals table (``paper`` protocol), thresholds as floats."""
    iv = iv.assign(threshold=iv["threshold"].map(results.threshold_value))
    iv = iv[(iv["scenario"] == SCENARIO) & (iv["metric"] == "recall") & (iv["k"] == 1)]
    return iv[iv["protocol"] == PAPER] if "protocol" in iv.columns else iv


def synth_intervals(figure_dirs: list[Path]) -> pd.DataFrame:
    """Scenario-1 recall@1 rows of the mini-Hypersim studies' ``intervals.csv`` (``paper`` protocol), the first
    folder holding a (method, threshold) giving it."""
    parts = [recall1(pd.read_csv(f / "intervals.csv")) for f in figure_dirs if (f / "intervals.csv").is_file()]
    if not parts:
        return pd.DataFrame(columns=bootstrap.INTERVAL_COLUMNS)
    return pd.concat(parts, ignore_index=True).drop_duplicates(["method", "threshold"], keep="first")


def best_thresholds(iv: pd.DataFrame, synth: pd.DataFrame) -> pd.DataFrame:
    """Per graph encoder with more than one threshold: the threshold of its best mean recall@1 on the real folds
    (`iv`) and on the mini-Hypersim (`synth`, over the same thresholds)."""
    real = recall1(iv)
    rows = []
    for method, g in real.groupby("method", sort=False):
        if len(g) < 2:
            continue
        r = g.loc[g["mean"].idxmax()]
        sg = synth[(synth["method"] == method) & synth["threshold"].isin(g["threshold"])]
        sr = sg.loc[sg["mean"].idxmax()] if len(sg) == len(g) else None
        rows.append({"method": method, "real_threshold": float(r.threshold), "real_mean": float(r["mean"]),
                     "synth_threshold": math.nan if sr is None else float(sr.threshold),
                     "synth_mean": math.nan if sr is None else float(sr["mean"])})
    return pd.DataFrame(rows, columns=["method", "real_threshold", "real_mean", "synth_threshold", "synth_mean"])


def edge_penalty_markdown(t: pd.DataFrame, study: Study) -> str:
    """``edge_penalty.md`` of a study over folds: each encoder at every threshold minus itself without edges on the
    real folds beside the mini-Hypersim (the rows of `real_vs_synth` that compare an encoder with itself)."""
    own = t[t["a"] == t["b"]] if len(t) else t
    lines = [f"# The edge penalty on both legs ({study.name})", "",
             f"Each graph encoder at every threshold minus the same encoder without edges ({METRIC}, points, paired; "
             f"95 % bootstrap interval): on the real folds ({study.protocol.folds} folds by volume) and on the "
             f"mini-Hypersim (the committed studies' `edge_penalty.csv`). Negative: the edges cost the encoder. "
             f"Agreement: of the signs (as in `real_vs_synth.md`); sizes: whether the two intervals overlap, or which "
             f"leg's penalty lies beyond the other's.", "",
             "| encoder | threshold (m) | real folds | mini-Hypersim | agreement | sizes |",
             "| --- | --- | --- | --- | --- | --- |"]
    for r in own.itertuples():
        synth = "" if r.synth != r.synth else f"{tables.signed(r.synth)} {tables.fmt_ci(r.synth_lo, r.synth_hi)}"
        lines.append(f"| {r.a} | {tables.threshold_label(r.ta)} | {tables.signed(r.real)} "
                     f"{tables.fmt_ci(r.real_lo, r.real_hi)} | {synth} | {r.agreement} | {interval_relation(r)} |")
    return "\n".join(lines) + "\n"


def interval_relation(r) -> str:
    """Whether the real and the mini-Hypersim intervals of one comparison overlap (``overlap``), or which leg's
    difference lies wholly below the other's (``real folds lower``, ``mini-Hypersim lower``); '' without a synthetic
    number."""
    if r.synth != r.synth:
        return ""
    if r.real_hi < r.synth_lo:
        return "real folds lower"
    if r.synth_hi < r.real_lo:
        return "mini-Hypersim lower"
    return "overlap"


def base_fold_study(study: Study) -> Study | None:
    """The study `study` extends when that one is cross-validated by volume too (the same data at another
    training size), else None."""
    if not study.extends:
        return None
    base = load_study(study.extends)
    return base if base.protocol.split == "volumes" and base.graphs_root else None


def training_size_markdown(study: Study, base: Study, iv: pd.DataFrame, base_iv: pd.DataFrame) -> str:
    """``training_size.md``: recall@1 of each method and threshold at the base study's training size and at this
    study's, over the same folds."""
    def size(s: Study) -> str:
        n, seeds = s.dataset.train_settings, len(s.seeds)
        return f"{'every training setting' if n is None else f'{n} training settings'} x " \
               f"{s.dataset.train_frames_per_setting} frames, {seeds} seed{'s' if seeds > 1 else ''}"

    mine, theirs = recall1(iv), recall1(base_iv)
    lines = [f"# Training size ({base.name} against {study.name})", "",
             f"Recall@1 (%), scenario 1, mean over {study.protocol.folds} folds by volume [95 % bootstrap interval]: "
             f"`{base.name}` ({size(base)}) and `{study.name}` ({size(study)}); the paper's number beside.", "",
             f"| method | threshold (m) | {base.name} | {study.name} | paper |", "| --- | --- | --- | --- | --- |"]
    paper = paper_recall1()
    for r in theirs.itertuples():
        m = mine[(mine["method"] == r.method) & (mine["threshold"] == r.threshold)]
        pp = paper.get(r.threshold) if r.method == "gcn" else None
        lines.append(f"| {r.method} | {tables.threshold_label(r.threshold)} | {mean_ci(r.mean, r.ci_lo, r.ci_hi)} | "
                     + ("" if m.empty else mean_ci(m["mean"].iloc[0], m["ci_lo"].iloc[0], m["ci_hi"].iloc[0]))
                     + f" | {'' if pp is None else format(pp, '.1f')} |")
    return "\n".join(lines) + "\n"


def reproduces_markdown(study: Study, rvs: pd.DataFrame, best: pd.DataFrame,
                        sizes: list[tuple[str, pd.DataFrame]], minis: list[tuple[str, pd.DataFrame]]) -> str:
    """``reproduces.md``: does the paper's threshold result hold? Per threshold the paper's recall@1 (scenario 1),
    the real folds at each training size of `sizes` (``(label, intervals)``, `study`'s among them), and the
    mini-Hypersim's `gcn` at each training size of `minis` (``(label, scenario-1 recall@1 rows)``, the study of the
    comparisons first); then one generated sentence per comparison the paper makes (each threshold against no
    edges, and the best threshold: `study`'s `rvs` and `best`) saying whether the two legs agree."""
    paper = paper_recall1()
    gcn = lambda t: t[t["method"] == "gcn"]  # noqa: E731
    real = [(label, gcn(recall1(x))) for label, x in sizes]
    mini = [(label, gcn(x)) for label, x in minis]
    lines = [f"Recall@1 (%) of the paper's GCN on ground truth at each threshold: the paper's number, the real "
             f"published graphs cross-validated by volume ({study.protocol.folds} folds of the development set, "
             f"mean [95 % bootstrap interval over folds, settings, queries and seeds]) and the mini-Hypersim (its "
             f"test split: 16 settings) at each training size (training settings x frames of each).", "",
             "| threshold (m) | paper | " + " | ".join(f"real folds, {label}" for label, _ in real) + " | "
             + " | ".join(f"mini-Hypersim, {label}" for label, _ in mini) + " |",
             "| --- | ---: |" + " ---: |" * (len(real) + len(mini))]
    thresholds = sorted(set().union(*[set(x["threshold"]) for _, x in real]))
    for t in thresholds:
        cells = []
        for _, x in real + mini:
            r = x[x["threshold"] == t]
            cells.append("" if r.empty else mean_ci(r["mean"].iloc[0], r["ci_lo"].iloc[0], r["ci_hi"].iloc[0]))
        lines.append(f"| {tables.threshold_label(t)} | {'' if t not in paper else format(paper[t], '.1f')} | "
                     + " | ".join(cells) + " |")
    lines += ["", f"What the paper's comparisons say on each leg (`{study.name}` and the mini-Hypersim at "
                  f"{mini[0][0] if mini else 'its size'}; paired differences in points, `real_vs_synth.md`):", ""]
    for r in (rvs[(rvs["a"] == "gcn") & (rvs["b"] == "gcn")].itertuples() if len(rvs) else []):
        verdict = {"agree": "the legs agree", "agree: neither significant": "the legs agree: neither differs from 0",
                   "no synthetic number": "the mini-Hypersim has no such cell"}.get(r.agreement,
                                                                                  f"the legs {r.agreement}")
        synth_txt = "" if r.synth != r.synth else \
            f", the mini-Hypersim {tables.signed(r.synth)} {tables.fmt_ci(r.synth_lo, r.synth_hi)}"
        lines.append(f"- {_at(r.ta)} against no edges: the real folds "
                     f"{tables.signed(r.real)} {tables.fmt_ci(r.real_lo, r.real_hi)}{synth_txt}; {verdict}.")
    b = best[best["method"] == "gcn"] if len(best) else best
    if len(b):
        r = b.iloc[0]
        same = r.synth_threshold == r.real_threshold
        synth_txt = "" if r.synth_threshold != r.synth_threshold else \
            f", on the mini-Hypersim {tables.threshold_label(r.synth_threshold)} ({r.synth_mean:.1f})"
        lines.append(f"- The best threshold: on the real folds {tables.threshold_label(r.real_threshold)} "
                     f"({r.real_mean:.1f}){synth_txt}"
                     + ("" if r.synth_threshold != r.synth_threshold else
                        ("; the same on both legs." if same else "; the legs differ."))
                     + (f" The paper's best: {tables.threshold_label(max(paper, key=paper.get))}." if paper else ""))
    return "\n".join(lines) + "\n"


def write(study: Study | None, out: Path, n_boot: int = bootstrap.N_BOOT) -> dict[str, Path]:
    """The fold outputs of a study with folds by volume into `out` (nothing for any other study). With the release
    split beside the folds, the release split's ``intervals.csv`` must be there already
    (`monolib.report.write.write_report` writes it first). A study of folds only (``protocol.release_split:
    false``) writes its tables over folds as its ``intervals.csv`` too (what `monolib verify` compares), its claims
    (``params/claims.yaml``, evaluated over folds), ``edge_penalty.md``, ``reproduces.md``, and, when it extends
    another study over folds, ``training_size.md``."""
    if study is None or study.protocol.split != "volumes":
        return {}
    only_folds = study.folds_only
    written: dict[str, Path] = {}
    fid = fold_fidelity(study)
    io.write_text(out / "folds.csv", tables.csv_text(fid))
    io.write_text(out / "folds.md", fidelity_markdown(fid, study))
    written.update(folds_csv=out / "folds.csv", folds_md=out / "folds.md")
    qv = fold_query_table(study)
    if qv.empty:
        log.warning("%s: no fold has a finished cell: no tables over folds", study.name)
        return written
    fboot = bootstrap.FoldBootstrap.for_queries(qv, n_boot)
    iv = bootstrap.fold_intervals(qv, fboot)
    io.write_text(out / "folds_intervals.csv", tables.csv_text(iv))
    if only_folds:
        io.write_text(out / "intervals.csv", tables.csv_text(iv))
        written["intervals"] = out / "intervals.csv"
        release = pd.DataFrame(columns=bootstrap.INTERVAL_COLUMNS)
    else:
        release = pd.read_csv(out / "intervals.csv") if (out / "intervals.csv").is_file() else pd.DataFrame(
            columns=bootstrap.INTERVAL_COLUMNS)
    release = results.only_protocol(release.assign(threshold=release["threshold"].map(results.threshold_value)),
                                    PAPER)
    for name, metric in (("folds_table1_recall", "recall"), ("folds_table2_precision", "precision")):
        t = fold_tables(iv, release, metric)
        io.write_text(out / f"{name}.csv", tables.csv_text(t))
        io.write_text(out / f"{name}.md", tables_markdown(t, metric, study))
        written[name] = out / f"{name}.md"
    dirs = synth_figures()
    rvs = real_vs_synth(study, qv, fboot, dirs)
    synth = synth_intervals(dirs)
    best = best_thresholds(iv, synth)
    io.write_text(out / "real_vs_synth.csv", tables.csv_text(rvs))
    io.write_text(out / "real_vs_synth.md", real_vs_synth_markdown(rvs, study, best))
    written.update(real_vs_synth=out / "real_vs_synth.md")
    penalty = "edge_penalty" if only_folds else "folds_edge_penalty"
    io.write_text(out / f"{penalty}.md", edge_penalty_markdown(rvs, study))
    written[penalty] = out / f"{penalty}.md"
    if not only_folds:
        return written
    # the claims of a study over folds: evaluated on the folds, with the fold-level bootstrap
    written.update(claims.write(study.name, out, qv, iv, {PAPER: fboot}, n_boot=n_boot,
                                grid={c.name for c in grid(study)}))
    sizes = [(size_label(study), iv)]
    base = base_fold_study(study)
    base_iv_path = paths.figures_dir(base.name) / "intervals.csv" if base is not None else None
    if base_iv_path is not None and base_iv_path.is_file():
        base_iv = pd.read_csv(base_iv_path)
        io.write_text(out / "training_size.md", training_size_markdown(study, base, iv, base_iv))
        written["training_size"] = out / "training_size.md"
        sizes.insert(0, (size_label(base), base_iv))
    minis = [(size_label(load_study(SYNTH_STUDY, check_files=False)), synth)]
    io.write_text(out / "reproduces.md", reproduces_markdown(study, rvs, best, sizes, minis))
    written["reproduces"] = out / "reproduces.md"
    return written


def _at(t: float) -> str:
    """'1 m', 'every pair joined (∞)': a threshold in a sentence."""
    return "every pair joined (∞)" if math.isinf(t) else f"{tables.threshold_label(t)} m"


def size_label(study: Study) -> str:
    """A study's training size as the tables name it: ``48 x 20`` (settings x frames per setting) or ``all x 100``."""
    n = study.dataset.train_settings
    return f"{'all' if n is None else n} x {study.dataset.train_frames_per_setting}"
