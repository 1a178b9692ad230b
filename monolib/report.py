"""The report stage: merge every cell of a study into Table 1, Table 2 and the figures.

Everything here reads files the cells wrote (``runs/<study>/cells/<method>/<scenario>__t<threshold>__s<seed>/``:
``cell.json``, ``rankings.csv``, ``protocol.csv``), never notebook outputs, and writes through the atomic helpers
of :mod:`monolib.io`, so a re-run on unchanged cells reproduces the same bytes.

Reference numbers
-----------------
``monolib/data/paper_tables.csv`` is a transcription of the paper's published Table 1 (recall@1/5/10) and
Table 2 (precision@2/4/6) from ``shared/docs/paper.md`` (columns ``scenario, threshold, metric, k, value, source``;
thresholds ``1, 2, 5, 10, inf``; values in percent). They are the paper's single-run numbers, not ours. Note that
the paper's own Table 1 is not monotone in k for Scenario 4 at 5 m (recall@5 87.5 > recall@10 86.3), which is
impossible for recall over one fixed ranking; it is transcribed as printed.

Metric definitions (the design's protocol)
------------------------------------------
A query's candidates are its own setting's positives plus every frame of the other settings.
``recall@k``: share of queries with at least one frame of their own setting in the top k.
``precision@k``: mean over queries of (own-setting frames in the top k) / k. Values in percent.
"""
from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd

from monolib import io, paths

log = logging.getLogger(__name__)

INF = math.inf
METRICS = ("recall", "precision")
RESULT_COLUMNS = ["method", "scenario", "threshold", "seed", "metric", "k", "value"]
SUMMARY_KEYS = ["method", "scenario", "threshold", "metric", "k"]
RANKING_COLUMNS = ["query", "query_setting", "rank", "match", "match_setting", "distance"]
PROTOCOL_COLUMNS = ["frame", "setting", "role"]
IMAGE_SCENARIO = "rgb"          # the scenario name image-only baselines are written under
TABLES = {"recall": ("table1_recall", "Table 1: Recall at k (%)"),
          "precision": ("table2_precision", "Table 2: Precision at k (%)")}

RgbOf = Callable[[str], Optional[np.ndarray]]


class ProtocolError(ValueError):
    """A cell's rankings break the evaluation protocol; the message names the query and the match."""


# ---- small helpers ---------------------------------------------------------------------------------------------

def _natural_key(text: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(text))]


def _threshold(value) -> float:
    """1 / 1.0 / '1' -> 1.0; 'inf' / 'Infinity' / inf -> inf."""
    return float(value)


def threshold_label(t: float, tex: bool = False) -> str:
    """The threshold as the paper prints it: 1, 2, 5, 10, ∞ (``$\\infty$`` in TeX), 2.5."""
    if t is None or (isinstance(t, float) and math.isnan(t)):
        return "–" if not tex else "--"
    if math.isinf(t):
        return r"$\infty$" if tex else "∞"
    return f"{t:g}"


def _method_order(methods) -> list[str]:
    from monolib.methods import METHODS

    registry = list(METHODS)
    return sorted(set(methods), key=lambda m: (registry.index(m) if m in registry else len(registry), m))


def _is_image(method: str, scenario: str) -> bool:
    from monolib.methods import METHODS

    if method in METHODS:
        return METHODS[method][0] == "image"
    return scenario == IMAGE_SCENARIO


def _cells_root(study_name: str) -> Path:
    return paths.study_dir(study_name) / "cells"


# ---- collect ---------------------------------------------------------------------------------------------------

def cell_files(study_name: str) -> list[Path]:
    """Every ``cell.json`` of a study, sorted."""
    return sorted(_cells_root(study_name).glob("*/*/cell.json"))


def collect(study_name: str) -> pd.DataFrame:
    """All cells of a study in long format: one row per number.

    Columns ``method, scenario, threshold (float, inf for 'inf'), seed, metric ('recall'|'precision'), k, value``
    (percent), sorted by method, scenario (natural order), threshold, seed, metric, k. Raises FileNotFoundError
    when the study has no cell yet.
    """
    files = cell_files(study_name)
    if not files:
        raise FileNotFoundError(f"{_cells_root(study_name)}: no cell.json found; run the study's cells first")
    rows = []
    for f in files:
        cell = io.read_json(f)
        try:
            base = (str(cell["method"]), str(cell["scenario"]), _threshold(cell["threshold"]), int(cell["seed"]))
            metrics = cell["metrics"]
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{f}: not a valid cell.json ({exc!r})") from exc
        for name, value in metrics.items():
            metric, _, k = name.partition("@")
            if metric not in METRICS or not k.isdigit():
                continue
            rows.append((*base, metric, int(k), float(value)))
    df = pd.DataFrame(rows, columns=RESULT_COLUMNS)
    return _sort(df, ["method", "scenario", "threshold", "seed", "metric", "k"])


def _sort(df: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    def key(col: pd.Series):
        if col.name == "scenario":
            return col.map(lambda s: tuple((0, x, "") if isinstance(x, int) else (1, 0, x) for x in _natural_key(s)))
        if col.name == "method":
            order = _method_order(col.unique())
            return col.map(order.index)
        return col

    return df.sort_values(by, key=key, kind="mergesort").reset_index(drop=True)


def recorded_labels(study_name: str) -> dict[str, str]:
    """``{scenario: label}`` as the cells recorded them (``scenario_label`` in cell.json)."""
    out: dict[str, str] = {}
    for f in cell_files(study_name):
        cell = io.read_json(f)
        if cell.get("scenario_label"):
            out.setdefault(str(cell["scenario"]), str(cell["scenario_label"]))
    return dict(sorted(out.items(), key=lambda kv: _natural_key(kv[0])))


def labels_of(study) -> dict[str, str]:
    """``{scenario: label}`` from a loaded study (`monolib.params.Study`)."""
    return {name: (sc.label or name) for name, sc in study.scenarios.items()}


class RgbReader:
    """``rgb_of(frame_key) -> uint8 (H, W, 3)`` on a study's dataset, opened at the first call.

    A frame (or a dataset) that cannot be read gives None and one warning, so Figure 5 shows a grey placeholder
    instead of losing the whole report.
    """

    def __init__(self, study):
        self.study = study
        self._ds = None
        self._failed: Optional[str] = None

    def __call__(self, key: str) -> Optional[np.ndarray]:
        from monolib import dataset
        from monolib.io import DataFileError

        if self._failed is not None:
            return None
        try:
            if self._ds is None:
                self._ds = dataset.open_dataset(self.study)
            return self._ds.frame_by_key(key).rgb
        except (DataFileError, OSError, ValueError) as exc:
            if self._ds is None:
                self._failed = str(exc)
            log.warning("figure 5: no image for %s (%s)", key, exc)
            return None


def rgb_reader(study) -> RgbOf:
    """``rgb_of(frame_key) -> uint8 (H, W, 3)`` on the study's dataset (a `Study` or a study name); see `RgbReader`."""
    from monolib import params

    if isinstance(study, (str, Path)):
        study = params.load_study(study)
    return RgbReader(study)


# ---- recomputing the metrics -----------------------------------------------------------------------------------

def _check_columns(df: pd.DataFrame, columns: list[str], what: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what}: missing columns {missing} (have {list(df.columns)})")


def hit_matrix(rankings: pd.DataFrame) -> tuple[pd.Index, np.ndarray]:
    """(queries, hits): ``hits[i, r]`` is True when query i's rank r+1 candidate is from the query's setting."""
    _check_columns(rankings, RANKING_COLUMNS, "rankings")
    codes, queries = pd.factorize(rankings["query"], sort=True)
    ranks = rankings["rank"].to_numpy(dtype=int)
    if len(ranks) and ranks.min() < 1:
        raise ValueError("rankings: ranks start at 1")
    depth = int(ranks.max()) if len(ranks) else 0
    hits = np.zeros((len(queries), depth), dtype=bool)
    hits[codes, ranks - 1] = (rankings["match_setting"].to_numpy() == rankings["query_setting"].to_numpy())
    return queries, hits


def recompute_metrics(rankings: pd.DataFrame, recall_k, precision_k,
                      positives_per_setting: int | Mapping[str, int] | pd.Series | None = None) -> dict[str, float]:
    """recall@k and precision@k (percent) recomputed from a cell's ``rankings.csv``, vectorised.

    ``positives_per_setting`` None (default, the paper's definition): precision@k divides by k. Given (one number,
    or a mapping setting -> number of positives), it divides by ``min(k, positives of the query's setting)``, the
    best reachable share when a setting has fewer positives than k. Raises ValueError when a k exceeds the
    depth of the rankings (the cells store the top 10).
    """
    queries, hits = hit_matrix(rankings)
    ks = [int(k) for k in recall_k] + [int(k) for k in precision_k]
    if ks and max(ks) > hits.shape[1]:
        raise ValueError(f"rankings: k={max(ks)} needs the top {max(ks)}, the rankings hold the top {hits.shape[1]}")
    if len(queries) == 0:
        raise ValueError("rankings: no query")
    found = np.cumsum(hits, axis=1)     # own-setting frames within the top r+1
    out: dict[str, float] = {}
    for k in recall_k:
        out[f"recall@{int(k)}"] = float(100.0 * np.mean(found[:, int(k) - 1] > 0))
    if positives_per_setting is not None:
        setting_of = rankings.drop_duplicates("query").set_index("query")["query_setting"].reindex(queries)
        if isinstance(positives_per_setting, (int, np.integer, float)):
            npos = np.full(len(queries), float(positives_per_setting))
        else:
            npos = setting_of.map(pd.Series(positives_per_setting)).to_numpy(dtype=float)
            if np.isnan(npos).any():
                raise ValueError(f"positives_per_setting: no count for settings "
                                 f"{sorted(set(setting_of[np.isnan(npos)]))}")
    for k in precision_k:
        k = int(k)
        den = np.minimum(k, npos) if positives_per_setting is not None else float(k)
        out[f"precision@{k}"] = float(100.0 * np.mean(found[:, k - 1] / den))
    return out


def check_protocol(rankings: pd.DataFrame, protocol: pd.DataFrame, positives: Optional[int] = None) -> dict:
    """Raise `ProtocolError` when a cell's rankings break the protocol drawn in its ``protocol.csv``.

    Checked: every ranked query is a protocol query of the setting it claims; settings agree with frame keys;
    (query, rank) and (query, match) are unique; no query retrieves itself; a candidate of the query's own setting
    is one of that setting's positives (never another query, nor a frame outside the draw); no setting has more
    than ``positives`` positives (when given). Returns counts ``{"queries", "settings", "positives"}``.
    """
    _check_columns(rankings, RANKING_COLUMNS, "rankings")
    _check_columns(protocol, PROTOCOL_COLUMNS, "protocol")

    def fail(mask: pd.Series, msg: str, frame: pd.DataFrame = rankings):
        if mask.any():
            row = frame[mask.to_numpy()].iloc[0]
            raise ProtocolError(f"{msg} ({int(mask.sum())} rows; first: {row.to_dict()})")

    roles = protocol["role"].astype(str)
    fail(~roles.isin(["query", "positive"]), "protocol: role must be 'query' or 'positive'", protocol)
    fail(protocol["frame"].duplicated(), "protocol: a frame is listed twice", protocol)
    fail(protocol["frame"].astype(str).str.split("/").str[0] != protocol["setting"].astype(str),
         "protocol: a frame's key does not start with its setting", protocol)
    counts = protocol[roles == "positive"].groupby("setting").size()
    if positives is not None and (counts > positives).any():
        bad = counts[counts > positives]
        raise ProtocolError(f"protocol: settings with more than {positives} positives: {bad.to_dict()}")

    role_of = protocol.set_index("frame")["role"]
    setting_of = protocol.set_index("frame")["setting"]
    q_role = rankings["query"].map(role_of)
    fail(q_role != "query", "rankings: a ranked query is not a query of the protocol")
    fail(rankings["query"].map(setting_of) != rankings["query_setting"], "rankings: query_setting disagrees with the protocol")
    fail(rankings["match"].astype(str).str.split("/").str[0] != rankings["match_setting"].astype(str),
         "rankings: match_setting disagrees with the match's frame key")
    fail(rankings.duplicated(["query", "rank"]), "rankings: a (query, rank) pair appears twice")
    fail(rankings.duplicated(["query", "match"]), "rankings: a query retrieves the same frame twice")
    fail(rankings["match"] == rankings["query"], "rankings: a query retrieves itself")
    own = rankings["match_setting"] == rankings["query_setting"]
    m_role = rankings["match"].map(role_of)
    fail(own & (m_role == "query"), "rankings: a query retrieves another query of its own setting")
    fail(own & (m_role != "positive"), "rankings: a query retrieves a frame of its own setting outside the positives")
    return {"queries": int(rankings["query"].nunique()), "settings": int(protocol["setting"].nunique()),
            "positives": int((roles == "positive").sum())}


# ---- summary and the paper's numbers ---------------------------------------------------------------------------

def summary(results: pd.DataFrame) -> pd.DataFrame:
    """Mean, sample std (ddof 1; NaN when n = 1) and n over seeds per (method, scenario, threshold, metric, k)."""
    g = results.groupby(SUMMARY_KEYS, sort=False)["value"]
    out = g.agg(mean="mean", std="std", n="count").reset_index()
    return _sort(out, SUMMARY_KEYS)


def paper_tables() -> pd.DataFrame:
    """The paper's Table 1 and Table 2 (``monolib/data/paper_tables.csv``); thresholds as floats (inf)."""
    df = pd.read_csv(paths.DATA / "paper_tables.csv")
    df["threshold"] = df["threshold"].astype(float)
    df["k"] = df["k"].astype(int)
    df["value"] = df["value"].astype(float)
    return df


# ---- tables ----------------------------------------------------------------------------------------------------

def _table_frame(results: pd.DataFrame, metric: str) -> pd.DataFrame:
    """The machine-readable table: method, scenario, threshold, k, mean, std, n, paper (+ layout helpers)."""
    s = summary(results[results["metric"] == metric])
    paper = paper_tables()
    paper = paper[paper["metric"] == metric][["scenario", "threshold", "k", "value"]].rename(columns={"value": "paper"})
    paper["method"] = "gcn"     # the paper's numbers are its GCN's
    s = s.merge(paper, on=["method", "scenario", "threshold", "k"], how="left")
    s["image"] = [_is_image(m, sc) for m, sc in zip(s["method"], s["scenario"])]
    # graph methods first (method, scenario, threshold), image baselines below
    s["_img"] = s["image"].astype(int)
    s = _sort(s, ["_img", "method", "scenario", "threshold", "k"]).drop(columns="_img")
    return s


def _fmt(mean: float, std: float, n: int) -> str:
    if mean is None or not np.isfinite(mean):
        return "–"
    if n > 1 and np.isfinite(std):
        return f"{mean:.1f} ± {std:.1f}"
    return f"{mean:.1f}"


def _layout(results: pd.DataFrame, metric: str, scenario_labels: Mapping[str, str]):
    """Rows of the paper's layout: one per (method, scenario, threshold), cells per k, best marked."""
    t = _table_frame(results, metric)
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
        rows.append({
            "method": method, "scenario": scenario, "label": label, "image": image,
            "threshold": None if image else threshold,
            "cells": {k: (g.loc[k, "mean"], g.loc[k, "std"], int(g.loc[k, "n"]), bool(g.loc[k, "best"]))
                      if k in g.index else None for k in ks},
            "paper": {k: (g.loc[k, "paper"] if k in g.index else np.nan) for k in ks},
        })
    return t, ks, rows


def _n_note(t: pd.DataFrame) -> str:
    ns = sorted(t["n"].unique())
    if len(ns) == 1:
        n = int(ns[0])
        return f"n = {n} seed{'s' if n != 1 else ''}" + ("" if n > 1 else " (mean only)")
    return f"n = {int(ns[0])}–{int(ns[-1])} seeds (see the csv)"


def _caption(metric: str, t: pd.DataFrame, tex: bool = False) -> str:
    pm, inf = (r"$\pm$", r"$\infty$") if tex else ("±", "∞")
    ours = "Ours: one seed" if set(t["n"]) == {1} else f"Ours: mean {pm} std over seeds, {_n_note(t)}"
    return (f"{ours}; paper: the published single-run number "
            f"(GCN rows, thresholds 1, 2, 5, 10, {inf}). "
            f"Bold: best mean per method and scenario for each k.")


def _md_table(metric: str, results, scenario_labels) -> str:
    t, ks, rows = _layout(results, metric, scenario_labels)
    name, title = TABLES[metric][0], TABLES[metric][1]
    has_paper = t["paper"].notna().any()
    head = ["method", "data", "threshold (m)"] + [f"k={k}" for k in ks]
    if has_paper:
        head += [f"paper k={k}" for k in ks]
    lines = [f"**{title}.** {_caption(metric, t)}", "",
             "| " + " | ".join(head) + " |",
             "|" + "|".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + "|"]
    prev = None
    for r in rows:
        group = (r["method"], r["scenario"])
        first = group != prev
        prev = group
        cells = []
        for k in ks:
            c = r["cells"][k]
            text = "–" if c is None else _fmt(*c[:3])
            cells.append(f"**{text}**" if c is not None and c[3] else text)
        line = [r["method"] if first else "", r["label"] if first else "", threshold_label(r["threshold"])] + cells
        if has_paper:
            line += [f"{r['paper'][k]:.1f}" if np.isfinite(r["paper"][k]) else "" for k in ks]
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines) + "\n"


_TEX_ESCAPE = {"&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$", "{": r"\{", "}": r"\}", "~": r"\~{}",
               "^": r"\^{}", "±": r"$\pm$", "∞": r"$\infty$", "–": "--"}


def _tex(text: str) -> str:
    return "".join(_TEX_ESCAPE.get(ch, ch) for ch in str(text))


def _tex_table(metric: str, results, scenario_labels) -> str:
    t, ks, rows = _layout(results, metric, scenario_labels)
    name, title = TABLES[metric]
    has_paper = t["paper"].notna().any()
    nk = len(ks)
    cols = "lll" + "r" * nk + ("r" * nk if has_paper else "")
    out = [r"\begin{table}[t]", r"\centering", r"\small",
           rf"\caption{{\textbf{{{_tex(title)}.}} {_caption(metric, t, tex=True)}}}",
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
        cells = []
        for k in ks:
            c = r["cells"][k]
            text = "--" if c is None else _tex(_fmt(*c[:3]))
            cells.append(rf"\textbf{{{text}}}" if c is not None and c[3] else text)
        line = [_tex(r["method"]) if first else "", _tex(r["label"]) if first else "",
                threshold_label(r["threshold"], tex=True)] + cells
        if has_paper:
            line += [f"{r['paper'][k]:.1f}" if np.isfinite(r["paper"][k]) else "" for k in ks]
        out.append(" & ".join(line) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out) + "\n"


def _csv_table(metric: str, results) -> str:
    t = _table_frame(results, metric)[["method", "scenario", "threshold", "k", "mean", "std", "n", "paper"]].copy()
    t["threshold"] = t["threshold"].map(paths.threshold_tag)
    for c in ("mean", "std", "paper"):
        t[c] = t[c].round(4)
    return t.to_csv(index=False, lineterminator="\n")


def table_markdown(results: pd.DataFrame, metric: str, scenario_labels: Optional[Mapping[str, str]] = None) -> str:
    """Table 1 (``metric='recall'``) or Table 2 (``'precision'``) as markdown."""
    return _md_table(metric, results, scenario_labels or {})


def write_tables(results: pd.DataFrame, out_dir: str | Path,
                 scenario_labels: Optional[Mapping[str, str]] = None) -> dict[str, Path]:
    """Write ``table1_recall.{md,csv,tex}`` and ``table2_precision.{md,csv,tex}`` into `out_dir`.

    Rows: method / scenario x threshold, image baselines below ("RGB only"); columns: k (ours, mean ± std over
    seeds, or the mean alone when n = 1) then the paper's published number for the GCN rows. Best mean per
    (method, scenario, k) in bold (compared at the printed precision). The csv has ``method, scenario, threshold,
    k, mean, std, n, paper``. Returns ``{"table1_md": path, ...}``.
    """
    out_dir = Path(out_dir)
    labels = dict(scenario_labels or {})
    written: dict[str, Path] = {}
    for metric, (name, _) in TABLES.items():
        if not (results["metric"] == metric).any():
            log.warning("no %s numbers in the results: %s not written", metric, name)
            continue
        short = name.split("_")[0]
        for ext, text in (("md", _md_table(metric, results, labels)), ("csv", _csv_table(metric, results)),
                          ("tex", _tex_table(metric, results, labels))):
            path = out_dir / f"{name}.{ext}"
            io.write_text(path, text)
            written[f"{short}_{ext}"] = path
    return written


# ---- figures ---------------------------------------------------------------------------------------------------

def _figure(**kw):
    """A bare `matplotlib.figure.Figure`: rendered by Agg on save, independent of pyplot's (or a notebook's)
    backend, and never left open in pyplot's figure manager."""
    from matplotlib.figure import Figure

    return Figure(**kw)


def fig_recall_vs_threshold(results: pd.DataFrame, path: str | Path, method: str = "gcn", k: int = 1,
                            scenario_labels: Optional[Mapping[str, str]] = None) -> Path:
    """recall@k against the edge threshold: one line per scenario (mean, error bars = std over seeds), the
    paper's values as faint dotted lines in the same colour, image baselines as horizontal dashed lines."""
    import matplotlib

    labels = dict(scenario_labels or {})
    s = summary(results[(results["metric"] == "recall") & (results["k"] == k)])
    ours = s[(s["method"] == method) & ~s["scenario"].eq(IMAGE_SCENARIO)]
    paper = paper_tables()
    paper = paper[(paper["metric"] == "recall") & (paper["k"] == k)]
    thresholds = sorted(set(ours["threshold"]) | (set(paper["threshold"]) if method == "gcn" else set()))
    xpos = {t: i for i, t in enumerate(thresholds)}
    scenarios = sorted(ours["scenario"].unique(), key=_natural_key)
    colours = matplotlib.colormaps["tab10"]

    fig = _figure(figsize=(6.4, 4.2))
    ax = fig.subplots()
    for i, sc in enumerate(scenarios):
        g = ours[ours["scenario"] == sc].sort_values("threshold")
        x = [xpos[t] for t in g["threshold"]]
        ax.errorbar(x, g["mean"], yerr=g["std"].fillna(0.0).to_numpy(), color=colours(i), marker="o", capsize=3,
                    label=f"{sc}: {labels.get(sc, sc)}")
        if method == "gcn":
            p = paper[paper["scenario"] == sc].sort_values("threshold")
            if len(p):
                ax.plot([xpos[t] for t in p["threshold"]], p["value"], color=colours(i), linestyle=":", alpha=0.45,
                        marker=".", label=f"{sc} (paper)")
    base = s[[_is_image(m, sc) for m, sc in zip(s["method"], s["scenario"])]]
    for j, (m, g) in enumerate(base.groupby("method", sort=True)):
        ax.axhline(float(g["mean"].mean()), color="0.35", linestyle="--", linewidth=1.2,
                   dashes=(5 + 2 * j, 3), label=f"{m} (RGB only)")
    ax.set_xticks(range(len(thresholds)), [threshold_label(t) for t in thresholds])
    ax.set_xlabel("edge distance threshold (m)")
    ax.set_ylabel(f"recall@{k} (%)")
    ax.set_ylim(0, 100)
    spread = "one seed" if set(s["n"]) <= {1} else f"error bars: std over seeds, {_n_note(s)}"
    ax.set_title(f"{method}: recall@{k} vs edge threshold ({spread})", fontsize=9)
    ax.grid(alpha=0.3)
    handles, names = ax.get_legend_handles_labels()
    rank = lambda name: 1 if name.endswith("(paper)") else 2 if name.endswith("(RGB only)") else 0
    order = sorted(range(len(names)), key=lambda i: (rank(names[i]), i))
    ax.legend([handles[i] for i in order], [names[i] for i in order], fontsize=7, loc="upper left",
              bbox_to_anchor=(1.01, 1.0), frameon=False)
    return io.save_figure(fig, path)


def _read_rankings(cell: Path) -> pd.DataFrame:
    f = cell / "rankings.csv"
    if not f.is_file():
        raise FileNotFoundError(f"{f}: no rankings; is the cell finished?")
    return pd.read_csv(f)


def match_cells(study_name: str, results: Optional[pd.DataFrame] = None, method: str = "gcn",
                threshold: Optional[float] = None, seed: Optional[int] = None) -> dict[str, tuple[float, int, Path]]:
    """``{scenario: (threshold, seed, cell folder)}`` used for Figure 5: per scenario the given threshold, or the
    one with the best mean recall@1 (ties: the smallest threshold); the given seed, or the smallest one."""
    results = collect(study_name) if results is None else results
    r = results[(results["method"] == method) & (results["metric"] == "recall") & (results["k"] == 1)]
    if r.empty:
        raise FileNotFoundError(f"{_cells_root(study_name) / method}: no {method} cell with recall@1")
    out = {}
    for sc in sorted(r["scenario"].unique(), key=_natural_key):
        g = r[r["scenario"] == sc]
        if threshold is not None:
            t = float(threshold)
        else:
            m = g.groupby("threshold")["value"].mean()
            t = float(m[m == m.max()].index.min())
        seeds = sorted(g[g["threshold"] == t]["seed"].unique())
        if not seeds:
            continue
        sd = int(seed) if seed is not None else int(seeds[0])
        out[sc] = (t, sd, paths.cell_dir(study_name, method, sc, t, sd))
    return out


def pick_queries(top1: Mapping[str, pd.DataFrame], n: int = 3) -> list[str]:
    """Deterministic queries for Figure 5 from the top-1 rows of each scenario: two hard ones (fewest scenarios
    right) around an easy one (most scenarios right), each from a different setting (as far as possible)."""
    frames = list(top1.values())
    common = set(frames[0]["query"])
    for f in frames[1:]:
        common &= set(f["query"])
    if not common:
        common = set(frames[0]["query"])
    q = pd.DataFrame({"query": sorted(common)})
    q["setting"] = q["query"].str.split("/").str[0]
    right = np.zeros(len(q), dtype=int)
    for f in frames:
        f = f.drop_duplicates("query").set_index("query")
        right += (f["match_setting"] == f["query_setting"]).reindex(q["query"], fill_value=False).to_numpy(dtype=int)
    q["right"] = right
    easy = q.sort_values(["right", "query"], ascending=[False, True], kind="mergesort")
    hard = q.sort_values(["right", "query"], ascending=[True, True], kind="mergesort")
    chosen: list[str] = []
    used: set[str] = set()
    for pool in [easy] + [hard] * max(0, n - 1):
        pick = pool[~pool["query"].isin(chosen) & ~pool["setting"].isin(used)]
        if pick.empty:
            pick = pool[~pool["query"].isin(chosen)]
        if pick.empty:
            break
        chosen.append(pick["query"].iloc[0])
        used.add(pick["setting"].iloc[0])
    if len(chosen) > 1:       # the paper's layout: a hard one (top), the easy one, the other hard ones
        chosen = [chosen[1], chosen[0], *chosen[2:]]
    return chosen


def _bordered(img: Optional[np.ndarray], colour, shape=(96, 128)) -> np.ndarray:
    if img is None:
        img = np.full((*shape, 3), 128, dtype=np.uint8)
    img = np.asarray(img)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3].astype(np.uint8)
    if colour is None:
        return img
    w = max(2, round(min(img.shape[:2]) / 16))
    out = np.empty((img.shape[0] + 2 * w, img.shape[1] + 2 * w, 3), dtype=np.uint8)
    out[:] = np.asarray(colour, dtype=np.uint8)
    out[w:-w, w:-w] = img
    return out


GREEN, RED = (30, 170, 60), (210, 35, 35)


def fig_matches(study_name: str, rgb_of: RgbOf, path: str | Path, method: str = "gcn",
                results: Optional[pd.DataFrame] = None, threshold: Optional[float] = None,
                seed: Optional[int] = None, queries: Optional[list[str]] = None, n_queries: int = 3,
                scenario_labels: Optional[Mapping[str, str]] = None) -> Path:
    """The paper's Figure 5: rows = queries, columns = the query then each scenario's top-1 match, framed green
    when the match is from the query's setting and red otherwise.

    Cells come from `match_cells` (per scenario the best threshold by mean recall@1 and the smallest seed, unless
    given); queries from `pick_queries` unless given. ``rgb_of(frame_key)`` returns a uint8 (H, W, 3) image (None:
    a grey placeholder).
    """
    labels = dict(scenario_labels or {})
    cells = match_cells(study_name, results, method, threshold, seed)
    top1 = {}
    for sc, (_, _, cell) in cells.items():
        r = _read_rankings(cell)
        top1[sc] = r[r["rank"] == 1].drop_duplicates("query").reset_index(drop=True)
    chosen = list(queries) if queries else pick_queries(top1, n_queries)
    if not chosen:
        raise ValueError(f"{study_name}: no query to show")
    scen = list(cells)
    ncol = 1 + len(scen)
    fig = _figure(figsize=(2.1 * ncol, 1.85 * len(chosen) + 0.4))
    axes = fig.subplots(len(chosen), ncol, squeeze=False)
    for i, q in enumerate(chosen):
        ax = axes[i][0]
        ax.imshow(_bordered(rgb_of(q), None))
        ax.set_ylabel(q.replace("/", "\n", 1), fontsize=6)
        if i == 0:
            ax.set_title("query", fontsize=8)
        for j, sc in enumerate(scen, start=1):
            ax = axes[i][j]
            row = top1[sc][top1[sc]["query"] == q]
            if row.empty:
                ax.imshow(_bordered(None, (160, 160, 160)))
                ax.set_xlabel("not a query here", fontsize=6)
            else:
                row = row.iloc[0]
                ok = row["match_setting"] == row["query_setting"]
                ax.imshow(_bordered(rgb_of(row["match"]), GREEN if ok else RED))
                ax.set_xlabel(str(row["match"]), fontsize=5.5, color="darkgreen" if ok else "darkred")
            if i == 0:
                t, sd, _ = cells[sc]
                ax.set_title(f"{sc}: {labels.get(sc, sc)}\n(t = {threshold_label(t)} m, seed {sd})", fontsize=6.5)
    for ax in np.ravel(axes):
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
    fig.suptitle(f"Top-1 match per scenario ({method}); green: same setting, red: another setting", fontsize=8)
    fig.tight_layout()
    return io.save_figure(fig, path)


# ---- the whole report ------------------------------------------------------------------------------------------

def write_report(study_name: str, rgb_of: Optional[RgbOf] = None,
                 scenario_labels: Optional[Mapping[str, str]] = None, method: str = "gcn") -> dict[str, Path]:
    """Collect a study's cells and write into `monolib.paths.figures_dir(study)`: ``results.csv``, Table 1 and 2
    (md, csv, tex), ``recall_vs_threshold.png`` and ``fig5_matches.png`` (skipped when `rgb_of` is None or the
    study has no `method` cell). Labels default to the ``scenario_label`` the cells recorded.
    Returns ``{"results": path, "table1_md": path, ..., "recall_vs_threshold": path, "fig5_matches": path}``.
    """
    out = paths.figures_dir(study_name)
    results = collect(study_name)
    labels = {**recorded_labels(study_name), **dict(scenario_labels or {})}
    written: dict[str, Path] = {}
    io.write_text(out / "results.csv", results.to_csv(index=False, float_format="%.6g", lineterminator="\n"))
    written["results"] = out / "results.csv"
    written.update(write_tables(results, out, labels))
    written["recall_vs_threshold"] = fig_recall_vs_threshold(results, out / "recall_vs_threshold.png", method,
                                                             scenario_labels=labels)
    if rgb_of is not None and (results["method"] == method).any():
        written["fig5_matches"] = fig_matches(study_name, rgb_of, out / "fig5_matches.png", method, results=results,
                                              scenario_labels=labels)
    log.info("report of %s written to %s", study_name, out)
    return written

