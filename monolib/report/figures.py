"""The report's figures: recall against the edge threshold, the paper's Figure 5 (top-1 matches), recall of dim vs
bright settings, recall against the depth scale, and recall on both protocols.

Each figure is a bare `matplotlib.figure.Figure` (independent of pyplot's or a notebook's backend) saved through
`monolib.io.save_figure`, so re-saving an unchanged figure changes no byte.
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd

from monolib import io, params, paths
from monolib.data import dataset
from monolib.io import DataFileError
from monolib.params import PAPER
from monolib.report.results import (
    IMAGE_SCENARIO, SUMMARY_KEYS, cells_root, collect, is_image, natural_key, only_protocol, paper_tables, protocols_in,
    read_rankings, split_protocols
)
from monolib.report.bootstrap import N_BOOT, summary
from monolib.report.tables import n_note, signed, threshold_label

log = logging.getLogger(__name__)

RgbOf = Callable[[str], Optional[np.ndarray]]
GREEN, RED = (30, 170, 60), (210, 35, 35)


def new_figure(**kw):
    """A bare `matplotlib.figure.Figure`: rendered by Agg on save, independent of pyplot's (or a notebook's)
    backend, and never left open in pyplot's figure manager."""
    from matplotlib.figure import Figure

    return Figure(**kw)


def metres(t: float) -> str:
    """'1 m', '∞ m', '0 (no edges)': a threshold in a figure's text."""
    return threshold_label(t) if t == 0 else f"{threshold_label(t)} m"


def _tick(t: float) -> str:
    return threshold_label(t).replace(" (", "\n(")


# ---- recall against the edge threshold -------------------------------------------------------------------------

def fig_recall_vs_threshold(results: pd.DataFrame, path: str | Path, method: str = "gcn", k: int = 1,
                            scenario_labels: Optional[Mapping[str, str]] = None,
                            intervals: Optional[pd.DataFrame] = None, protocol: str = PAPER) -> Path:
    """recall@k against the edge threshold (0: no edges) on one protocol (default ``paper``): one line per
    scenario (mean, error bars = std over seeds, or the 95 % bootstrap interval when `intervals` are given), the
    paper's values as faint dotted lines in the same colour (``paper`` protocol only), image baselines as
    horizontal dashed lines."""
    import matplotlib

    labels = dict(scenario_labels or {})
    results = only_protocol(results if "protocol" in results.columns else results.assign(protocol=PAPER), protocol)
    s = summary(results[(results["metric"] == "recall") & (results["k"] == k)])
    if intervals is not None:
        intervals = only_protocol(intervals if "protocol" in intervals.columns else intervals.assign(protocol=PAPER),
                                  protocol)
        s = s.merge(intervals[SUMMARY_KEYS + ["ci_lo", "ci_hi"]], on=SUMMARY_KEYS, how="left")
    ours = s[(s["method"] == method) & ~s["scenario"].eq(IMAGE_SCENARIO)]
    paper = paper_tables()
    paper = paper[(paper["metric"] == "recall") & (paper["k"] == k)]
    if protocol != PAPER:
        paper = paper.iloc[0:0]
    thresholds = sorted(set(ours["threshold"]) | (set(paper["threshold"]) if method == "gcn" else set()))
    xpos = {t: i for i, t in enumerate(thresholds)}
    scenarios = sorted(ours["scenario"].unique(), key=natural_key)
    colours = matplotlib.colormaps["tab10"]

    fig = new_figure(figsize=(6.4, 4.2))
    ax = fig.subplots()
    for i, sc in enumerate(scenarios):
        g = ours[ours["scenario"] == sc].sort_values("threshold")
        dodge = 0.06 * (i - (len(scenarios) - 1) / 2) if intervals is not None else 0.0
        x = [xpos[t] + dodge for t in g["threshold"]]
        if intervals is not None:
            yerr = np.vstack([g["mean"] - g["ci_lo"], g["ci_hi"] - g["mean"]])
            yerr = np.nan_to_num(yerr, nan=0.0)
        else:
            yerr = g["std"].fillna(0.0).to_numpy()
        ax.errorbar(x, g["mean"], yerr=yerr, color=colours(i), marker="o", capsize=3,
                    label=f"{sc}: {labels.get(sc, sc)}")
        if method == "gcn":
            p = paper[paper["scenario"] == sc].sort_values("threshold")
            if len(p):
                ax.plot([xpos[t] for t in p["threshold"]], p["value"], color=colours(i), linestyle=":", alpha=0.45,
                        marker=".", label=f"{sc} (paper)")
    base = s[[is_image(m, sc) for m, sc in zip(s["method"], s["scenario"])]]
    for j, (m, g) in enumerate(base.groupby("method", sort=True)):
        ax.axhline(float(g["mean"].mean()), color="0.35", linestyle="--", linewidth=1.2,
                   dashes=(5 + 2 * j, 3), label=f"{m} (RGB only)")
    ax.set_xticks(range(len(thresholds)), [_tick(t) for t in thresholds])
    ax.set_xlabel("edge distance threshold (m)")
    ax.set_ylabel(f"recall@{k} (%)")
    ax.set_ylim(0, 100)
    if intervals is not None:
        spread = f"error bars: 95% bootstrap intervals, {n_note(s).replace(' (mean only)', '')}"
    else:
        spread = "one seed" if set(s["n"]) <= {1} else f"error bars: std over seeds, {n_note(s)}"
    where = "" if protocol == PAPER else f", {protocol} protocol"
    ax.set_title(f"{method}: recall@{k} vs edge threshold{where} ({spread})", fontsize=9)
    ax.grid(alpha=0.3)
    handles, names = ax.get_legend_handles_labels()

    def rank(name):
        return 1 if name.endswith("(paper)") else 2 if name.endswith("(RGB only)") else 0

    order = sorted(range(len(names)), key=lambda i: (rank(names[i]), i))
    ax.legend([handles[i] for i in order], [names[i] for i in order], fontsize=7, loc="upper left",
              bbox_to_anchor=(1.01, 1.0), frameon=False)
    return io.save_figure(fig, path)


# ---- Figure 5: top-1 matches -----------------------------------------------------------------------------------

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
    if isinstance(study, (str, Path)):
        study = params.load_study(study)
    return RgbReader(study)


def match_cells(study_name: str, results: Optional[pd.DataFrame] = None, method: str = "gcn",
                threshold: Optional[float] = None, seed: Optional[int] = None) -> dict[str, tuple[float, int, Path]]:
    """``{scenario: (threshold, seed, cell folder)}`` used for Figure 5: per scenario the given threshold, or the
    one with the best mean recall@1 of the ``paper`` protocol (ties: the smallest threshold); the given seed, or
    the smallest one."""
    results = collect(study_name) if results is None else results
    results = only_protocol(results, PAPER)
    r = results[(results["method"] == method) & (results["metric"] == "recall") & (results["k"] == 1)]
    if r.empty:
        raise FileNotFoundError(f"{cells_root(study_name) / method}: no {method} cell with recall@1")
    out = {}
    for sc in sorted(r["scenario"].unique(), key=natural_key):
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


def fig_matches(study_name: str, rgb_of: RgbOf, path: str | Path, method: str = "gcn",
                results: Optional[pd.DataFrame] = None, threshold: Optional[float] = None,
                seed: Optional[int] = None, queries: Optional[list[str]] = None, n_queries: int = 3,
                scenario_labels: Optional[Mapping[str, str]] = None) -> Path:
    """The paper's Figure 5 (``paper`` protocol): rows = queries, columns = the query then each scenario's top-1
    match, framed green when the match is from the query's setting and red otherwise.

    Cells come from `match_cells` (per scenario the best threshold by mean recall@1 and the smallest seed, unless
    given); queries from `pick_queries` unless given. ``rgb_of(frame_key)`` returns a uint8 (H, W, 3) image (None:
    a grey placeholder).
    """
    labels = dict(scenario_labels or {})
    cells = match_cells(study_name, results, method, threshold, seed)
    top1 = {}
    for sc, (_, _, cell) in cells.items():
        r = split_protocols(read_rankings(cell))[PAPER]
        top1[sc] = r[r["rank"] == 1].drop_duplicates("query").reset_index(drop=True)
    chosen = list(queries) if queries else pick_queries(top1, n_queries)
    if not chosen:
        raise ValueError(f"{study_name}: no query to show")
    scen = list(cells)
    ncol = 1 + len(scen)
    fig = new_figure(figsize=(2.1 * ncol, 1.85 * len(chosen) + 0.4))
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
                ax.set_title(f"{sc}: {labels.get(sc, sc)}\n(t = {metres(t)}, seed {sd})",
                             fontsize=6.5)
    for ax in np.ravel(axes):
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
    fig.suptitle(f"Top-1 match per scenario ({method}); green: same setting, red: another setting", fontsize=8)
    fig.tight_layout()
    return io.save_figure(fig, path)


# ---- the controlled comparisons --------------------------------------------------------------------------------

def fig_recall_by_light(table: pd.DataFrame, path: str | Path, method: str = "gcn", k: int = 1,
                        n_boot: int = N_BOOT) -> Path:
    """Bars: recall@k of queries in bright and in dim test settings per scenario (`method` at each scenario's best
    threshold) and per image baseline (`monolib.report.comparisons.light_table`); error bars: 95 %
    bootstrap intervals."""
    t = table[table["light"].isin(["dim", "bright"])]
    groups = list(dict.fromkeys(zip(t["method"], t["scenario"], t["threshold"])))
    fig = new_figure(figsize=(max(4.8, 1.1 * len(groups) + 2.0), 3.8))
    ax = fig.subplots()
    width = 0.38
    colours = {"bright": "#f2b134", "dim": "#3b4a6b"}
    for j, light in enumerate(("bright", "dim")):
        xs, ys, err = [], [], [[], []]
        n_set = sorted(set(t[t["light"] == light]["n_settings"]))
        for i, key_ in enumerate(groups):
            r = t[(t["method"] == key_[0]) & (t["scenario"] == key_[1]) & (t["threshold"] == key_[2])
                  & (t["light"] == light)]
            if r.empty or not np.isfinite(r["mean"].iloc[0]):
                continue
            r = r.iloc[0]
            xs.append(i + (j - 0.5) * width)
            ys.append(r["mean"])
            err[0].append(r["mean"] - r["ci_lo"])
            err[1].append(r["ci_hi"] - r["mean"])
        label = f"{light} settings (n = {', '.join(str(int(n)) for n in n_set)})"
        ax.bar(xs, ys, width, yerr=np.asarray(err), capsize=3, color=colours[light], label=label,
               error_kw={"elinewidth": 1.0})
    diff = table[table["light"] == "bright - dim"]
    for i, key_ in enumerate(groups):
        d = diff[(diff["method"] == key_[0]) & (diff["scenario"] == key_[1]) & (diff["threshold"] == key_[2])]
        if len(d) and np.isfinite(d["mean"].iloc[0]):
            d = d.iloc[0]
            ax.text(i, 101, f"Δ {signed(d['mean'])}\n[{signed(d['ci_lo'])}, {signed(d['ci_hi'])}]",
                    ha="center", va="bottom", fontsize=6.5)
    names = [f"{m}\n{sc}, t = {threshold_label(th)}" if not is_image(m, sc) else f"{m}\n(RGB only)"
             for m, sc, th in groups]
    ax.set_xticks(range(len(groups)), names, fontsize=7)
    ax.set_ylabel(f"recall@{k} (%)")
    ax.set_ylim(0, 116)
    ax.set_yticks(range(0, 101, 20))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(f"recall@{k}: queries of dim vs bright test settings\n({method} at each scenario's best threshold by "
                 f"mean recall@{k}; error bars: 95% bootstrap intervals, B = {n_boot}; Δ: bright − dim [95% interval])",
                 fontsize=8)
    return io.save_figure(fig, path)


def fig_recall_vs_depth_scale(table: pd.DataFrame, path: str | Path, k: int = 1, n_boot: int = N_BOOT) -> Path:
    """recall@k against the depth scale factor (log axis), one line per threshold, one panel per (depth,
    semantic) source pair (`monolib.report.comparisons.depth_scale_table`); error bars: 95 % bootstrap intervals."""
    import matplotlib

    pairs = list(dict.fromkeys(zip(table["depth"], table["semantic"])))
    fig = new_figure(figsize=(4.6 * len(pairs) + 1.6, 3.8))
    axes = np.ravel(fig.subplots(1, len(pairs), squeeze=False))
    colours = matplotlib.colormaps["viridis"]
    thresholds = sorted(table["threshold"].unique())
    for ax, (depth, semantic) in zip(axes, pairs):
        g = table[(table["depth"] == depth) & (table["semantic"] == semantic)]
        scales = sorted(g["depth_scale"].unique())
        for i, t in enumerate(thresholds):
            h = g[g["threshold"] == t].sort_values("depth_scale")
            if h.empty:
                continue
            jitter = 1.0 + 0.012 * (i - (len(thresholds) - 1) / 2)
            ax.errorbar(h["depth_scale"] * jitter, h["mean"],
                        yerr=np.vstack([h["mean"] - h["ci_lo"], h["ci_hi"] - h["mean"]]), marker="o", capsize=3,
                        color=colours(i / max(1, len(thresholds) - 1) * 0.9), label=f"t = {metres(t)}")
        ax.set_xscale("log")
        ax.set_xticks(scales, [f"{s:g}" for s in scales])
        ax.minorticks_off()
        ax.axvline(1.0, color="0.6", linewidth=0.8, linestyle=":")
        ax.set_xlabel("depth scale factor")
        ax.set_ylabel(f"recall@{k} (%)")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
        ax.set_title(f"depth: {depth}, semantics: {semantic}", fontsize=8)
    axes[-1].legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    method = table["method"].iloc[0] if len(table) else "gcn"
    fig.suptitle(f"{method}: recall@{k} vs depth scale (error bars: 95% bootstrap intervals, B = {n_boot})",
                 fontsize=8)
    return io.save_figure(fig, path)


def _group_name(m: str, sc: str, t: float) -> str:
    if is_image(m, sc):
        return f"{m}\n(RGB only)"
    return f"{m}\n{sc}, t = {metres(t)}"


def fig_protocols(table: pd.DataFrame, path: str | Path, k: int = 1, n_boot: int = N_BOOT) -> Path:
    """Bars: recall@k of each method (graph methods per scenario, at the best ``paper`` threshold) on each
    protocol, from the same cells (`monolib.report.comparisons.protocols_table`); error bars: 95 %
    bootstrap intervals."""
    import matplotlib

    groups = list(dict.fromkeys(zip(table["method"], table["scenario"], table["threshold"])))
    protos = protocols_in(table)
    fig = new_figure(figsize=(max(5.2, 0.95 * len(groups) + 2.4), 3.9))
    ax = fig.subplots()
    width = 0.8 / max(1, len(protos))
    colours = matplotlib.colormaps["tab10"]
    for j, p in enumerate(protos):
        xs, ys, err = [], [], [[], []]
        for i, (m, sc, t) in enumerate(groups):
            r = table[(table["method"] == m) & (table["scenario"] == sc) & (table["threshold"] == t)
                      & (table["protocol"] == p)]
            if r.empty:
                continue
            r = r.iloc[0]
            xs.append(i + (j - (len(protos) - 1) / 2) * width)
            ys.append(r["mean"])
            err[0].append(max(0.0, r["mean"] - r["ci_lo"]))
            err[1].append(max(0.0, r["ci_hi"] - r["mean"]))
        n_set = sorted(set(table.loc[table["protocol"] == p, "n_settings"]))
        ax.bar(xs, ys, width, yerr=np.asarray(err), capsize=2.5, color=colours(j),
               label=f"{p} ({', '.join(str(int(n)) for n in n_set)} settings)", error_kw={"elinewidth": 1.0})
    ax.set_xticks(range(len(groups)), [_group_name(m, sc, t) for m, sc, t in groups], fontsize=6.5)
    ax.set_ylabel(f"recall@{k} (%)")
    ax.set_ylim(0, 100)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(f"recall@{k} on both protocols, same trained encoders (graph methods at their best paper-protocol "
                 f"threshold;\nerror bars: 95% bootstrap intervals, B = {n_boot}; siblings: pairs of settings of one "
                 f"family)", fontsize=7.5)
    return io.save_figure(fig, path)
