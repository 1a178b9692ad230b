"""The report of a study cross-validated by volume (`protocol.split: volumes`), beside its release-split tables:

- ``folds_intervals.csv``: per (method, scenario, threshold, metric, k) the mean over folds and seeds and its 95 %
  interval resampling folds, test settings, queries and seeds (`monolib.report.statistics.FoldBootstrap`), ``paper``
  protocol;
- ``folds_table1_recall.{md,csv}``, ``folds_table2_precision.{md,csv}``: Tables 1-2 over the folds, the release
  split in its own column (its ``intervals.csv``, written by the report before), the paper's numbers beside;
- ``folds.md`` / ``folds.csv``: each fold's test volumes and the fidelity statistics of its test graphs (nodes per
  graph, label-set Jaccard, wall colour ratio; `monolib.graphs.fidelity.split_statistics`), so that a reader sees
  why folds differ;
- ``real_vs_synth.{md,csv}``: each scenario-1 comparison the tables make (each threshold against threshold 0; each
  variant against ``gcn`` at the variant's thresholds), its paired difference with interval on the real folds and on
  the mini-Hypersim (the committed quick study's ``threshold_tests.csv`` and ``encoder_ablation.csv``), and whether
  the two agree: the same sign with both significant, or neither significant.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path

import pandas as pd

from monolib import io, paths
from monolib.data.protocols import family
from monolib.graphs import fidelity, stage as scenegraphs
from monolib.params import PAPER, Study
from monolib.report import results, statistics, tables
from monolib.retrieval.grid import grid

log = logging.getLogger(__name__)
SCENARIO = "s1"          # the scenario of the published graphs (ground truth): the only one compared
SYNTH_STUDY = "quick"    # the committed mini-Hypersim study read for the synthetic side
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


def _ci(mean: float, lo: float, hi: float) -> str:
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
    head = ["method", "scenario", "threshold"] + [f"{metric}@{k} {c}" for k in ks for c in ("folds", "release",
                                                                                            "paper")]
    lines = [f"# {metric.capitalize()}@k over {study.protocol.folds} folds by volume ({study.name})", "",
             f"Mean over folds and seeds, 95 % bootstrap interval resampling folds, test settings, queries and seeds "
             f"(paper protocol: {study.protocol.settings} test settings of each fold); `release`: the release's own "
             f"split (its interval over settings, queries and seeds); `paper`: the paper's single-run number.", "",
             "| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    for (m, sc, th), g in t.groupby(["method", "scenario", "threshold"], sort=False):
        cells = []
        for k in ks:
            r = g[g["k"] == k]
            r = r.iloc[0] if len(r) else None
            cells += ["" if r is None else _ci(r.folds, r.folds_lo, r.folds_hi),
                      "" if r is None else _ci(r.release, r.release_lo, r.release_hi),
                      "" if r is None or r.paper != r.paper else f"{r.paper:.1f}"]
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
    lines = [f"# The folds of {study.name}", "",
             f"The volumes of the release's train/ and test/ dealt into {study.protocol.folds} folds by the study's "
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
    """The scenario-1 comparisons of the tables, ``(method a, threshold a, method b, threshold b)`` for a - b:
    ``gcn`` at each threshold against ``gcn`` at 0 (when the study has threshold 0), then each variant at each of
    its thresholds against ``gcn`` at the same threshold."""
    ts = [float(t) for t in study.thresholds]
    out = [("gcn", t, "gcn", 0.0) for t in ts if t != 0] if 0.0 in ts else []
    for name, v in study.variants.items():
        out += [(name, float(t), "gcn", float(t)) for t in (v.thresholds or ts) if float(t) in ts]
    return out


def synth_differences(figures: Path) -> pd.DataFrame:
    """The committed mini-Hypersim differences of the same comparisons, ``paper`` protocol, scenario 1:
    threshold t against 0 from ``threshold_tests.csv`` (rows whose best threshold is 0, and, negated, the row of 0
    against a best t: the paired bootstrap difference is antisymmetric), variants against ``gcn`` from
    ``encoder_ablation.csv``. Columns ``a, ta, b, tb, metric, k, diff, ci_lo, ci_hi, significant``."""
    tests = pd.read_csv(figures / "threshold_tests.csv")
    tests = tests[(tests["scenario"] == SCENARIO) & (tests["protocol"] == PAPER) & (tests["method"] == "gcn")]
    tests = tests.assign(threshold=tests["threshold"].map(results.threshold_value),
                         best_threshold=tests["best_threshold"].map(results.threshold_value))
    rows = []
    for r in tests.itertuples():
        if r.best_threshold == 0:
            rows.append(("gcn", r.threshold, "gcn", 0.0, r.metric, r.k, r.diff, r.ci_lo, r.ci_hi, r.significant))
        elif r.threshold == 0:
            rows.append(("gcn", r.best_threshold, "gcn", 0.0, r.metric, r.k, -r.diff, -r.ci_hi, -r.ci_lo,
                         r.significant))
    abl = pd.read_csv(figures / "encoder_ablation.csv")
    abl = abl[(abl["scenario"] == SCENARIO) & (abl["protocol"] == PAPER) & abl["diff_vs_base"].notna()]
    for r in abl.itertuples():
        t = results.threshold_value(r.threshold)
        rows.append((r.method, t, "gcn", t, r.metric, r.k, r.diff_vs_base, r.diff_lo, r.diff_hi, r.significant))
    return pd.DataFrame(rows, columns=["a", "ta", "b", "tb", "metric", "k", "diff", "ci_lo", "ci_hi", "significant"])


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


def real_vs_synth(study: Study, qv: pd.DataFrame, fboot: statistics.FoldBootstrap, figures: Path) -> pd.DataFrame:
    """Each comparison of `comparisons` on the real folds (`statistics.fold_paired_difference`) beside the
    mini-Hypersim's (`synth_differences`), with their agreement."""
    synth = synth_differences(figures)
    rows = []
    for a, ta, b, tb in comparisons(study):
        ra, rb = statistics.rows_of(qv, a, SCENARIO, ta), statistics.rows_of(qv, b, SCENARIO, tb)
        if ra.empty or rb.empty:
            continue
        for r in statistics.fold_paired_difference(ra, rb, fboot).itertuples():
            s = synth[(synth["a"] == a) & (synth["ta"] == ta) & (synth["b"] == b) & (synth["tb"] == tb)
                      & (synth["metric"] == r.metric) & (synth["k"] == r.k)]
            srow = s.iloc[0] if len(s) else None
            rows.append({"comparison": f"{a} at {tables.threshold_label(ta)} - {b} at {tables.threshold_label(tb)}",
                         "metric": f"{r.metric}@{r.k}", "real": r.diff, "real_lo": r.ci_lo, "real_hi": r.ci_hi,
                         "real_significant": r.significant, "n_folds": r.n_folds,
                         "synth": math.nan if srow is None else srow["diff"],
                         "synth_lo": math.nan if srow is None else srow.ci_lo,
                         "synth_hi": math.nan if srow is None else srow.ci_hi,
                         "synth_significant": None if srow is None else bool(srow.significant),
                         "agreement": agreement(pd.Series({"diff": r.diff, "significant": r.significant}), srow)})
    return pd.DataFrame(rows)


def real_vs_synth_markdown(t: pd.DataFrame, study: Study, figures: Path) -> str:
    lines = [f"# Real folds against the mini-Hypersim ({study.name})", "",
             f"Each scenario-1 comparison of the tables (paper protocol): the paired difference a - b in points, "
             f"with its 95 % bootstrap interval, on the real folds ({study.protocol.folds} folds by volume of the "
             f"published graphs; resampling folds, settings, queries and seeds) and on the mini-Hypersim (the "
             f"committed {SYNTH_STUDY} study, `{figures}`: `threshold_tests.csv`, `encoder_ablation.csv`). "
             f"They agree when the two have the same sign and both intervals exclude 0, or when neither does.", "",
             "| comparison | metric | real folds | mini-Hypersim | agreement |", "| --- | --- | --- | --- | --- |"]
    for r in t.itertuples():
        real = f"{tables.signed(r.real)} {tables.fmt_ci(r.real_lo, r.real_hi)}"
        synth = "" if r.synth != r.synth else f"{tables.signed(r.synth)} {tables.fmt_ci(r.synth_lo, r.synth_hi)}"
        lines.append(f"| {r.comparison} | {r.metric} | {real} | {synth} | {r.agreement} |")
    counts = t["agreement"].value_counts() if len(t) else pd.Series(dtype=int)
    lines += ["", "; ".join(f"{n} {name}" for name, n in counts.items()) or "no comparison with cells yet"]
    return "\n".join(lines) + "\n"


def write(study: Study | None, out: Path, n_boot: int = statistics.N_BOOT) -> dict[str, Path]:
    """The fold outputs of a study with folds by volume into `out` (nothing for any other study); the release
    split's ``intervals.csv`` must be there already (`monolib.report.write.write_report` writes it first)."""
    if study is None or study.protocol.split != "volumes":
        return {}
    written: dict[str, Path] = {}
    fid = fold_fidelity(study)
    io.write_text(out / "folds.csv", tables.csv_text(fid))
    io.write_text(out / "folds.md", fidelity_markdown(fid, study))
    written.update(folds_csv=out / "folds.csv", folds_md=out / "folds.md")
    qv = fold_query_table(study)
    if qv.empty:
        log.warning("%s: no fold has a finished cell: no tables over folds", study.name)
        return written
    fboot = statistics.FoldBootstrap.for_queries(qv, n_boot)
    iv = statistics.fold_intervals(qv, fboot)
    io.write_text(out / "folds_intervals.csv", tables.csv_text(iv))
    release = pd.read_csv(out / "intervals.csv") if (out / "intervals.csv").is_file() else pd.DataFrame(
        columns=statistics.INTERVAL_COLUMNS)
    release = results.only_protocol(release.assign(threshold=release["threshold"].map(results.threshold_value)),
                                    PAPER)
    for name, metric in (("folds_table1_recall", "recall"), ("folds_table2_precision", "precision")):
        t = fold_tables(iv, release, metric)
        io.write_text(out / f"{name}.csv", tables.csv_text(t))
        io.write_text(out / f"{name}.md", tables_markdown(t, metric, study))
        written[name] = out / f"{name}.md"
    figures = paths.figures_dir(SYNTH_STUDY)
    figures = figures.relative_to(paths.ROOT) if figures.is_relative_to(paths.ROOT) else figures
    rvs = real_vs_synth(study, qv, fboot, figures)
    io.write_text(out / "real_vs_synth.csv", tables.csv_text(rvs))
    io.write_text(out / "real_vs_synth.md", real_vs_synth_markdown(rvs, study, figures))
    written.update(real_vs_synth=out / "real_vs_synth.md")
    return written
