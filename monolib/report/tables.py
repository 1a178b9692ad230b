"""The report's tables: Table 1 (recall@k) and Table 2 (precision@k) in markdown, csv and TeX, the encoder ablation,
the two protocols side by side and the siblings protocol's confusions in markdown, and how a threshold, a mean and
an interval are printed.

Table 1 and 2 follow the paper's layout: one row per method / scenario x threshold, image baselines below
("RGB only"); columns k (ours: mean ± std over seeds, the 95 % bootstrap interval, a dagger on thresholds
significantly below the best of `monolib.report.comparisons.threshold_tests`), then the paper's published number beside
the GCN rows of the ``paper`` protocol (`monolib.report.results.paper_tables`).
"""
from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd

from monolib import io, paths
from monolib.params import PAPER, SIBLINGS
from monolib.report.results import (
    SUMMARY_KEYS, is_image, one_protocol_only, only_protocol, paper_tables, protocols_in, sort_rows
)
from monolib.report.bootstrap import N_BOOT, summary

log = logging.getLogger(__name__)

TABLES = {"recall": ("table1_recall", "Table 1: Recall at k (%)"),
          "precision": ("table2_precision", "Table 2: Precision at k (%)")}
DAGGER = "†"
STAR = "*"
NO_EDGES = "0 (no edges)"
PROTOCOL_NOTES = {
    PAPER: "Protocol `paper` (the paper's): each test setting is of another family (ai_VVV); a query's candidates "
           "are its setting's positives and every frame of the other settings.",
    SIBLINGS: "Protocol `siblings` (the paper's \"two neighbouring offices\", which it never tested): pairs of test "
              "settings of one family (same furniture and materials, another layout); a query's candidates are its "
              "setting's positives and every frame of the other settings, its sibling's included. Same trained "
              "encoders as the `paper` tables.",
}


# ---- how numbers are printed -----------------------------------------------------------------------------------

def threshold_label(t: float, tex: bool = False) -> str:
    """The threshold as the paper prints it: 1, 2, 5, 10, ∞ (``$\\infty$`` in TeX), 2.5; 0 (no edges: nodes
    only) as ``0 (no edges)``."""
    if t is None or (isinstance(t, float) and math.isnan(t)):
        return "–" if not tex else "--"
    if math.isinf(t):
        return r"$\infty$" if tex else "∞"
    if t == 0:
        return NO_EDGES
    return f"{t:g}"


def fmt_mean(mean: float, std: float, n: int) -> str:
    """'61.2 ± 3.4' (std over n > 1 seeds), '61.2' (one seed), '–' (none)."""
    if mean is None or not np.isfinite(mean):
        return "–"
    if n > 1 and np.isfinite(std):
        return f"{mean:.1f} ± {std:.1f}"
    return f"{mean:.1f}"


def fmt_ci(lo, hi) -> str:
    """'[58.0, 64.1]' ('' without an interval)."""
    if lo is None or hi is None or not (np.isfinite(lo) and np.isfinite(hi)):
        return ""
    return f"[{lo:.1f}, {hi:.1f}]"


def signed(x: float) -> str:
    """'+1.2', '−3.4' (a true minus sign), '–' when not finite."""
    return f"{x:+.1f}".replace("-", "−") if np.isfinite(x) else "–"


def n_note(t: pd.DataFrame) -> str:
    """'n = 3 seeds' of a summary (column ``n``)."""
    ns = sorted(t["n"].unique())
    if len(ns) == 1:
        n = int(ns[0])
        return f"n = {n} seed{'s' if n != 1 else ''}" + ("" if n > 1 else " (mean only)")
    return f"n = {int(ns[0])}–{int(ns[-1])} seeds (see the csv)"


_TEX_ESCAPE = {"&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$", "{": r"\{", "}": r"\}", "~": r"\~{}",
               "^": r"\^{}", "±": r"$\pm$", "∞": r"$\infty$", "–": "--", "†": r"$^\dagger$", "Δ": r"$\Delta$"}


def _tex(text: str) -> str:
    return "".join(_TEX_ESCAPE.get(ch, ch) for ch in str(text))


def csv_text(df: pd.DataFrame) -> str:
    """A frame as the report writes its csv files (6 significant digits, '\\n' line ends)."""
    return df.to_csv(index=False, float_format="%.6g", lineterminator="\n")


# ---- Table 1 and Table 2 ---------------------------------------------------------------------------------------

def _table_frame(results: pd.DataFrame, metric: str, iv: Optional[pd.DataFrame] = None,
                 tests: Optional[pd.DataFrame] = None) -> pd.DataFrame:
    """The machine-readable table of one protocol's rows: method, scenario, threshold, protocol, k, mean, std, n,
    [ci_lo, ci_hi,] paper, [worse_than_best] (+ layout helpers). The paper's numbers sit beside the ``paper``
    protocol only (the paper never ran the siblings protocol)."""
    if "protocol" not in results.columns:
        results = results.assign(protocol=PAPER)
    one_protocol_only(results, "table")
    on = ["method", "scenario", "threshold", "protocol", "k"]
    s = summary(results[results["metric"] == metric])
    if iv is not None:
        iv = iv if "protocol" in iv.columns else iv.assign(protocol=PAPER)
        ci = iv[iv["metric"] == metric][SUMMARY_KEYS + ["ci_lo", "ci_hi"]].drop(columns="metric")
        s = s.merge(ci, on=on, how="left")
    paper = paper_tables()
    paper = paper[paper["metric"] == metric][["scenario", "threshold", "k", "value"]].rename(columns={"value": "paper"})
    paper["method"] = "gcn"     # the paper's numbers are its GCN's, on its protocol
    paper["protocol"] = PAPER
    s = s.merge(paper, on=on, how="left")
    if tests is not None:
        tests = tests if "protocol" in tests.columns else tests.assign(protocol=PAPER)
        tt = tests[tests["metric"] == metric][on + ["significant"]]
        s = s.merge(tt.rename(columns={"significant": "worse_than_best"}), on=on, how="left")
        s["worse_than_best"] = s["worse_than_best"].astype("boolean").fillna(False).astype(bool)
    s["image"] = [is_image(m, sc) for m, sc in zip(s["method"], s["scenario"])]
    # graph methods first, by scenario (each variant right below the paper's gcn), image baselines below
    s["_img"] = s["image"].astype(int)
    s = sort_rows(s, ["_img", "scenario", "method", "threshold", "k"]).drop(columns="_img")
    return s


def _layout(results: pd.DataFrame, metric: str, scenario_labels: Mapping[str, str],
            iv: Optional[pd.DataFrame] = None, tests: Optional[pd.DataFrame] = None):
    """Rows of the paper's layout: one per (method, scenario, threshold), cells per k, best marked.

    A cell is ``{"mean", "std", "n", "best", "ci" (text, '' without intervals), "worse" (dagger)}``."""
    t = _table_frame(results, metric, iv, tests)
    ks = sorted(t["k"].unique())
    t["shown"] = t["mean"].round(1)
    best = t.groupby(["method", "scenario", "k"])["shown"].transform("max")
    size = t.groupby(["method", "scenario", "k"])["shown"].transform("size")
    t["best"] = (t["shown"] == best) & (size > 1)
    rows = []
    for (method, scenario, threshold), g in t.groupby(["method", "scenario", "threshold"], sort=False):
        g = g.set_index("k")
        image = bool(g["image"].iloc[0])
        label = "RGB only" if image else f"{scenario}: {scenario_labels.get(scenario, scenario)}"
        cells = {}
        for k in ks:
            if k not in g.index:
                cells[k] = None
                continue
            r = g.loc[k]
            cells[k] = {"mean": r["mean"], "std": r["std"], "n": int(r["n"]), "best": bool(r["best"]),
                        "ci": fmt_ci(r["ci_lo"], r["ci_hi"]) if "ci_lo" in g.columns else "",
                        "worse": bool(r["worse_than_best"]) if "worse_than_best" in g.columns else False}
        rows.append({
            "method": method, "scenario": scenario, "label": label, "image": image,
            "threshold": None if image else threshold, "cells": cells,
            "paper": {k: (g.loc[k, "paper"] if k in g.index else np.nan) for k in ks},
        })
    return t, ks, rows


CAMERA_NOTES = {
    "monograph": "the original Monograph code's back-projection (its 1024x768 camera, f 577.35 / 433.01 px, scaled "
                 "to the frames, Euclidean depth as z), in which the paper measured its thresholds",
    "exact": "each scene's own camera with planar depth (true metres; the paper's thresholds were measured in the "
             "original code's camera, where lengths come out 1.5-2 times longer)",
}


def camera_note(projections: Mapping[str, str]) -> str:
    """The caption's sentence on the camera of the graphs (`projections`: ``{scenario: projection}`` of the
    scenarios in the table)."""
    cameras = sorted(set(projections.values()))
    if not cameras:
        return ""
    if len(cameras) == 1:
        return f"Graphs and thresholds in the `{cameras[0]}` camera: {CAMERA_NOTES.get(cameras[0], cameras[0])}."
    return "Graphs and thresholds in the camera of each scenario: " + "; ".join(
        f"{sc} `{p}`" for sc, p in projections.items()) + "."


def _protocol_of(t: pd.DataFrame) -> str:
    return str(t["protocol"].iloc[0]) if "protocol" in t.columns and len(t) else PAPER


def protocol_note(name: str, protocol=None) -> str:
    """The sentence of a table's caption that says how its protocol chose the test settings (`protocol`: the
    study's `monolib.params.Protocol`, for the ``paper`` protocol on data without families by construction)."""
    if name == PAPER and protocol is not None and protocol.families is False:
        return (f"Protocol `paper` (the paper's): {protocol.settings} test settings taken in turn from each volume "
                "(ai_VVV) in name order, as the paper took 16 settings of a test split of few volumes; a query's "
                "candidates are its setting's positives and every frame of the other settings.")
    return PROTOCOL_NOTES.get(name, f"Protocol `{name}`.")


def _caption(metric: str, t: pd.DataFrame, tex: bool = False, n_boot: Optional[int] = None,
             note: Optional[str] = None) -> str:
    pm, inf, dag = (r"$\pm$", r"$\infty$", r"$^\dagger$") if tex else ("±", "∞", DAGGER)
    ours = "Ours: one seed" if set(t["n"]) == {1} else f"Ours: mean {pm} std over seeds, {n_note(t)}"
    protocol = _protocol_of(t)
    note = note or protocol_note(protocol)
    note = note.replace("`", "").replace("_", r"\_") if tex else note
    if t["paper"].notna().any():
        text = (f"{note} {ours}; paper: the published single-run number "
                f"(GCN rows, thresholds 1, 2, 5, 10, {inf}). ")
    else:
        text = f"{note} {ours}. "
    text += "Bold: best mean per method and scenario for each k."
    if (t["threshold"] == 0).any():
        text += " Threshold 0: no edges (the encoder sees the nodes only)."
    if "ci_lo" in t.columns:
        text += (f" [lo, hi]: 95% bootstrap interval of our mean ({n_boot or N_BOOT} resamples of test settings, "
                 f"of queries within each setting and of seeds, all with replacement).")
    if "worse_than_best" in t.columns:
        text += (f" {dag}: significantly below the best threshold of its method and scenario for this k (paired "
                 f"bootstrap of the difference on the same queries, 95% interval excluding 0; each threshold "
                 f"tested on its own, no correction for multiple comparisons).")
    return text.replace("%", r"\%") if tex else text


def _cell_text(c: Optional[dict], tex: bool) -> str:
    if c is None:
        return "--" if tex else "–"
    main = fmt_mean(c["mean"], c["std"], c["n"])
    if tex:
        main = _tex(main)
        text = rf"\textbf{{{main}}}" if c["best"] else main
        if c["ci"]:
            text += rf" {{\scriptsize {c['ci']}}}"
        return text + (r"$^\dagger$" if c["worse"] else "")
    text = f"**{main}**" if c["best"] else main
    if c["ci"]:
        text += f" {c['ci']}"
    return text + (DAGGER if c["worse"] else "")


def _title(metric: str, t: pd.DataFrame) -> str:
    protocol = _protocol_of(t)
    return TABLES[metric][1] + ("" if protocol == PAPER else f", {protocol} protocol")


def _md_table(metric: str, results, scenario_labels, iv=None, tests=None, n_boot=None, note=None) -> str:
    t, ks, rows = _layout(results, metric, scenario_labels, iv, tests)
    title = _title(metric, t)
    has_paper = t["paper"].notna().any()
    head = ["method", "data", "threshold (m)"] + [f"k={k}" for k in ks]
    if has_paper:
        head += [f"paper k={k}" for k in ks]
    lines = [f"**{title}.** {_caption(metric, t, n_boot=n_boot, note=note)}", "",
             "| " + " | ".join(head) + " |",
             "|" + "|".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + "|"]
    prev = None
    for r in rows:
        group = (r["method"], r["scenario"])
        first = group != prev
        prev = group
        cells = [_cell_text(r["cells"][k], tex=False) for k in ks]
        line = [r["method"] if first else "", r["label"] if first else "", threshold_label(r["threshold"])] + cells
        if has_paper:
            line += [f"{r['paper'][k]:.1f}" if np.isfinite(r["paper"][k]) else "" for k in ks]
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines) + "\n"


def _tex_table(metric: str, results, scenario_labels, iv=None, tests=None, n_boot=None, note=None) -> str:
    t, ks, rows = _layout(results, metric, scenario_labels, iv, tests)
    name, title = TABLES[metric][0] + table_suffix(_protocol_of(t)), _title(metric, t)
    has_paper = t["paper"].notna().any()
    nk = len(ks)
    cols = "lll" + "r" * nk + ("r" * nk if has_paper else "")
    out = [r"\begin{table}[t]", r"\centering", r"\small",
           rf"\caption{{\textbf{{{_tex(title)}.}} {_caption(metric, t, tex=True, n_boot=n_boot, note=note)}}}",
           rf"\label{{tab:{name}}}", rf"\begin{{tabular}}{{{cols}}}", r"\toprule"]
    group = rf" & & & \multicolumn{{{nk}}}{{c}}{{ours, $k$}}"
    rule = rf"\cmidrule(lr){{4-{3 + nk}}}"
    if has_paper:
        group += rf" & \multicolumn{{{nk}}}{{c}}{{paper, $k$}}"
        rule += rf"\cmidrule(lr){{{4 + nk}-{3 + 2 * nk}}}"
    out += [group + r" \\", rule]
    out.append("Method & Data & Threshold (m) & " + " & ".join(str(k) for k in ks * (2 if has_paper else 1)) + r" \\")
    out.append(r"\midrule")
    prev = None
    for r in rows:
        group_key = (r["method"], r["scenario"])
        first = group_key != prev
        if first and prev is not None:
            out.append(r"\midrule")
        prev = group_key
        cells = [_cell_text(r["cells"][k], tex=True) for k in ks]
        line = [_tex(r["method"]) if first else "", _tex(r["label"]) if first else "",
                threshold_label(r["threshold"], tex=True)] + cells
        if has_paper:
            line += [f"{r['paper'][k]:.1f}" if np.isfinite(r["paper"][k]) else "" for k in ks]
        out.append(" & ".join(line) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out) + "\n"


def _csv_table(metric: str, results, iv=None, tests=None) -> str:
    t = _table_frame(results, metric, iv, tests)
    cols = ["method", "scenario", "threshold", "k", "mean", "std", "n"]
    cols += ["ci_lo", "ci_hi"] if iv is not None else []
    cols += ["paper"] + (["worse_than_best"] if tests is not None else [])
    t = t[cols].copy()
    t["threshold"] = t["threshold"].map(paths.threshold_tag)
    for c in ("mean", "std", "paper", "ci_lo", "ci_hi"):
        if c in t.columns:
            t[c] = t[c].round(4)
    return t.to_csv(index=False, lineterminator="\n")


def table_markdown(results: pd.DataFrame, metric: str, scenario_labels: Optional[Mapping[str, str]] = None,
                   intervals: Optional[pd.DataFrame] = None, tests: Optional[pd.DataFrame] = None) -> str:
    """Table 1 (``metric='recall'``) or Table 2 (``'precision'``) as markdown."""
    return _md_table(metric, results, scenario_labels or {}, intervals, tests)


def table_suffix(protocol: str) -> str:
    """File-name suffix of a protocol's tables: '' for the paper protocol (the headline tables), else '_<name>'."""
    return "" if protocol == PAPER else f"_{protocol}"


def write_tables(results: pd.DataFrame, out_dir: str | Path,
                 scenario_labels: Optional[Mapping[str, str]] = None, intervals: Optional[pd.DataFrame] = None,
                 tests: Optional[pd.DataFrame] = None, n_boot: Optional[int] = None,
                 protocol: str = PAPER, note: Optional[str] = None) -> dict[str, Path]:
    """Write ``table1_recall.{md,csv,tex}`` and ``table2_precision.{md,csv,tex}`` of one protocol into `out_dir`
    (the ``paper`` protocol; another protocol's files end in ``_<protocol>``: ``table1_recall_siblings.md``, keys
    ``table1_siblings_md``...). `results` (`monolib.report.results.collect`), `intervals` and `tests`
    (`monolib.report.bootstrap`, `monolib.report.comparisons`) may hold every protocol: the rows of `protocol` are used.

    Rows: method / scenario x threshold, image baselines below ("RGB only"); columns: k (ours, mean ± std over
    seeds, or the mean alone when n = 1; with `intervals` (see `monolib.report.bootstrap.intervals`) followed by the
    95 % bootstrap interval ``[lo, hi]``; with `tests` (see `monolib.report.comparisons.threshold_tests`) a dagger on
    thresholds significantly below the best) then the paper's published number for the GCN rows. Best mean per
    (method, scenario, k) in bold (compared at the printed precision). The csv has ``method, scenario, threshold,
    k, mean, std, n, [ci_lo, ci_hi,] paper[, worse_than_best]``. `note`: the caption's sentence on how the
    protocol chose its settings (default: `protocol_note` of `protocol`). Returns ``{"table1_md": path, ...}``.
    """
    out_dir = Path(out_dir)
    labels = dict(scenario_labels or {})
    written: dict[str, Path] = {}
    results, intervals, tests = (only_protocol(f, protocol) for f in (results, intervals, tests))
    for metric, (name, _) in TABLES.items():
        name = name + table_suffix(protocol)
        if not (results["metric"] == metric).any():
            log.warning("no %s numbers in the results: %s not written", metric, name)
            continue
        short = name.split("_")[0] + table_suffix(protocol)
        for ext, text in (("md", _md_table(metric, results, labels, intervals, tests, n_boot, note)),
                          ("csv", _csv_table(metric, results, intervals, tests)),
                          ("tex", _tex_table(metric, results, labels, intervals, tests, n_boot, note))):
            path = out_dir / f"{name}.{ext}"
            io.write_text(path, text)
            written[f"{short}_{ext}"] = path
    return written


# ---- the encoder ablation and the two protocols ----------------------------------------------------------------

def ablation_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None,
                      base: str = "gcn", n_boot: int = N_BOOT, title: str = "Encoder ablation.") -> str:
    """``encoder_ablation.md`` of `monolib.report.comparisons.encoder_ablation`: rows = method x (scenario, threshold)
    (the base first), columns = each metric's ``mean [lo, hi]`` and its paired difference to the base
    ``Δ [lo, hi]`` (* when significant)."""
    labels = dict(scenario_labels or {})
    metrics = list(dict.fromkeys(f"{m}@{k}" for m, k in zip(table["metric"], table["k"])))
    head = ["method", "data", "threshold (m)"]
    for c in metrics:
        head += [c, f"Δ {c} vs {base}"]
    lines = [f"**{title}** Mean over seeds [95% bootstrap interval: {n_boot} resamples of test settings, "
             f"queries and seeds]. Δ: paired difference to `{base}` on the same seeds, settings and queries "
             f"[95% paired bootstrap interval]; {STAR}: the interval excludes 0 (no correction for multiple "
             f"comparisons).", "",
             "| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + "|"]
    prev = None
    for (m, sc, t), g in table.groupby(["method", "scenario", "threshold"], sort=False):
        g = g.assign(col=[f"{a}@{b}" for a, b in zip(g["metric"], g["k"])]).set_index("col")
        line = [f"`{m}`" if m != prev else "", f"{sc}: {labels.get(sc, sc)}", threshold_label(t)]
        prev = m
        for c in metrics:
            if c not in g.index:
                line += ["–", "–"]
                continue
            r = g.loc[c]
            line.append(f"{r['mean']:.1f} {fmt_ci(r['ci_lo'], r['ci_hi'])}")
            if m == base or not np.isfinite(r["diff_vs_base"]):
                line.append("–")
            else:
                line.append(f"{signed(r['diff_vs_base'])} [{signed(r['diff_lo'])}, {signed(r['diff_hi'])}]"
                            + (STAR if r["significant"] else ""))
        lines.append("| " + " | ".join(line) + " |")
    lines += ["", "Methods:"]
    for m, d in dict(zip(table["method"], table["description"])).items():
        lines.append(f"- `{m}`: {d}")
    return "\n".join(lines) + "\n"


def edge_penalty_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None,
                          n_boot: int = N_BOOT, title: str = "What the edges cost.") -> str:
    """``edge_penalty.md`` of `monolib.report.comparisons.edge_penalty`: a row per method and scenario, recall@k
    without edges, then at each threshold the paired difference to it ``Δ [lo, hi]`` (* when significant)."""
    labels = dict(scenario_labels or {})
    thresholds = sorted(table["threshold"].unique())
    k = int(table["k"].iloc[0]) if len(table) else 1
    head = ["method", "data", f"recall@{k} without edges"] + [f"Δ at {threshold_label(t)} m" for t in thresholds]
    lines = [f"**{title}** Recall@{k} on `paper` at each threshold minus recall@{k} of the same encoder without "
             f"edges (threshold 0: the nodes alone), paired on the same seeds, settings and queries [95% paired "
             f"bootstrap interval, {n_boot} resamples]; {STAR}: the interval excludes 0. Without edges the mean "
             f"over seeds [its interval is in intervals.csv].", "",
             "| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + "|"]
    for (m, sc), g in table.groupby(["method", "scenario"], sort=False):
        g = g.set_index("threshold")
        line = [f"`{m}`", f"{sc}: {labels.get(sc, sc)}", f"{g['no_edges'].iloc[0]:.1f}"]
        for t in thresholds:
            if t not in g.index:
                line.append("–")
                continue
            r = g.loc[t]
            line.append(f"{signed(r['diff'])} [{signed(r['ci_lo'])}, {signed(r['ci_hi'])}]"
                        + (STAR if r["significant"] else ""))
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines) + "\n"


def twin_rows(table: pd.DataFrame, axis: str, scenario_labels: Optional[Mapping[str, str]] = None,
              paper: Optional[Mapping[tuple, float]] = None) -> list[str]:
    """The per-scenario tables of `monolib.report.comparisons.twin_table` along `axis`: per method and threshold,
    recall@k of the scenario and of its twin, with the paired difference; with `paper` ({(scenario, threshold):
    the paper's number}) a last column with it on the `gcn` rows (blank where the paper has none)."""
    labels = dict(scenario_labels or {})
    lines = []
    for (sc, mine, pair, theirs), g in table.groupby(["scenario", axis, "pair", f"pair_{axis}"], sort=False):
        lines += [f"*{sc}: {labels.get(sc, sc)}*, `{mine}` against {pair} in `{theirs}`:", "",
                  f"| method | threshold (m) | {mine} | {theirs} | Δ {theirs} - {mine} |"
                  + (" paper |" if paper else ""),
                  "|---|---|---:|---:|---:|" + ("---:|" if paper else "")]
        prev = None
        for _, r in g.iterrows():
            diff = ("–" if not np.isfinite(r["diff"]) else
                    f"{signed(r['diff'])} [{signed(r['diff_lo'])}, {signed(r['diff_hi'])}]"
                    + (STAR if r["significant"] else ""))
            theirs_paper = paper.get((sc, float(r["threshold"]))) if paper and r["method"] == "gcn" else None
            lines.append(f"| {'`' + r['method'] + '`' if r['method'] != prev else ''} | "
                         f"{threshold_label(r['threshold'])} | {r['mean']:.1f} {fmt_ci(r['ci_lo'], r['ci_hi'])} | "
                         f"{r['pair_mean']:.1f} {fmt_ci(r['pair_ci_lo'], r['pair_ci_hi'])} | {diff} |"
                         + (f" {'' if theirs_paper is None else f'{theirs_paper:.1f}'} |" if paper else ""))
            prev = r["method"]
        lines.append("")
    return lines


def projection_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None,
                        n_boot: int = N_BOOT) -> str:
    """``projection.md`` of `monolib.report.comparisons.projection_table`: per method, scenario and threshold, recall@k
    in the scenario's camera and in its twin's, with the paired difference."""
    k = int(table["k"].iloc[0]) if len(table) else 1
    lines = [f"**The two cameras, threshold by threshold** (recall@{k}, `paper` protocol). The same encoder, "
             f"sources, seeds and threshold, the graphs built in the original Monograph code's camera (`monograph`: "
             f"f 577.35 / 433.01 px at 1024x768 scaled to the frames, Euclidean depth as z, lengths 1.5-2 times the "
             f"true ones) and in the exact one (`exact`: each scene's own camera, planar depth). Mean over seeds "
             f"[95% bootstrap interval, {n_boot} resamples of settings, queries and seeds]; Δ: paired difference "
             f"(twin - scenario) on the same seeds, settings and queries; {STAR}: its interval excludes 0. "
             f"Threshold 0 has no edges, so both cameras give the same graphs to the encoder (a control).", ""]
    return "\n".join(lines + twin_rows(table, "projection", scenario_labels))


def colour_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None,
                    n_boot: int = N_BOOT) -> str:
    """``colour.md`` of `monolib.report.comparisons.colour_table`: per method, scenario and threshold, recall@k with
    the node colours in the scenario's space and in its twin's, with the paired difference."""
    k = int(table["k"].iloc[0]) if len(table) else 1
    lines = [f"**The two colour spaces of the nodes, threshold by threshold** (recall@{k}, `paper` protocol). The same "
             f"encoder, sources, camera, seeds and threshold, each node's median R, G, B taken over Hypersim's HDR "
             f"`color.hdf5` (`hdr`: linear radiance, as the original code's and the published graphs hold it) or "
             f"over the frame's tonemapped image (`tonemapped`: each frame's brightness divided out, gamma 1/2.2, "
             f"0..1). The networks see the tonemapped image either way. Mean over seeds [95% bootstrap interval, "
             f"{n_boot} resamples of settings, queries and seeds]; Δ: paired difference (twin - scenario) on the same "
             f"seeds, settings and queries; {STAR}: its interval excludes 0; paper: the paper's number for its GCN "
             f"(Table 1, the original code's HDR colours).", ""]
    pt = paper_tables()
    pt = pt[(pt["metric"] == "recall") & (pt["k"] == k)]
    paper = {(r.scenario, float(r.threshold)): float(r.value) for r in pt.itertuples(index=False)}
    return "\n".join(lines + twin_rows(table, "colour", scenario_labels, paper))


def protocols_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None,
                       n_boot: int = N_BOOT) -> str:
    """``protocols.md`` of `monolib.report.comparisons.protocols_table`: one row per method (and scenario), recall@k on
    each protocol with its interval."""
    labels = dict(scenario_labels or {})
    protos = protocols_in(table)
    k = int(table["k"].iloc[0]) if len(table) else 1
    sizes = {p: (int(g["n_settings"].max()), int(g["n_queries"].max())) for p, g in table.groupby("protocol")}
    head = ["method", "data", "threshold (m)"] + [f"recall@{k} {p} ({sizes[p][0]} settings)" for p in protos]
    lines = [f"**Recall@{k} on both protocols**, from the same trained encoders (cells). `paper`: test settings of "
             f"different families (ai_VVV), the paper's protocol; `siblings`: pairs of settings of one family (same "
             f"furniture and materials, another layout), where a query's candidates include its sibling's frames. "
             f"Graph methods at the threshold with the best `paper` recall@{k} of their scenario. Mean over seeds "
             f"[95% bootstrap interval, {n_boot} resamples of settings, queries and seeds; each protocol resampled "
             f"on its own].", "",
             "| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * len(protos)) + "|"]
    for (m, sc, t), g in table.groupby(["method", "scenario", "threshold"], sort=False):
        g = g.set_index("protocol")
        image = is_image(m, sc)
        line = [m, "RGB only" if image else f"{sc}: {labels.get(sc, sc)}", "" if image else threshold_label(t)]
        for p in protos:
            line.append(f"{g.loc[p, 'mean']:.1f} {fmt_ci(g.loc[p, 'ci_lo'], g.loc[p, 'ci_hi'])}" if p in g.index
                        else "–")
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines) + "\n"


def confusions_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None) -> str:
    """``siblings_confusions.md`` of `monolib.report.comparisons.siblings_confusions`: one row per method (and
    scenario) of the protocols table, where its ``siblings`` queries' top-1 matches go (percent of queries over
    seeds) and the sibling share of its errors."""
    labels = dict(scenario_labels or {})
    protocol = _protocol_of(table) if len(table) else SIBLINGS
    head = ["method", "data", "threshold (m)", "queries", "right (%)", "sibling (%)", "other (%)",
            "sibling share of errors (%)"]

    def pct(x):
        return f"{x:.1f}" if np.isfinite(x) else "–"

    lines = [f"**Which settings the `{protocol}` protocol confuses**, from the same cells as the protocols table "
             f"(graph methods at the threshold with the best `paper` recall@1 of their scenario). Each query's top-1 "
             f"match is *right* (a frame of its own setting), *sibling* (a frame of the other setting of its family: "
             f"same furniture and materials, another layout) or *other* (a frame of another family); shares of the "
             f"queries of all seeds. Sibling share of errors: sibling / (sibling + other), the errors a query makes "
             f"in its own family.", "",
             "| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + "|"]
    for _, r in table.iterrows():
        image = is_image(r["method"], r["scenario"])
        line = [r["method"], "RGB only" if image else f"{r['scenario']}: {labels.get(r['scenario'], r['scenario'])}",
                "" if image else threshold_label(float(r["threshold"])), f"{int(r['queries'])}",
                pct(r["share_right"]), pct(r["share_sibling"]), pct(r["share_other"]),
                pct(float(r["sibling_share_of_errors"]))]
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines) + "\n"
