"""The report's comparison tables, each built on the paired bootstrap of `monolib.report.bootstrap`: every
threshold against its scenario's best (`threshold_tests`), what the edges cost each encoder (`edge_penalty`), the
encoder variants against the base (`encoder_ablation`), dim vs bright settings (`light_table`), depth scale
(`depth_scale_table`), a scenario's twin in another camera or colour space (`projection_table`, `colour_table`),
the two protocols side by side (`protocols_table`) and which settings the ``siblings`` protocol confuses
(`siblings_confusions`). Each returns a frame with the columns of its module constant (``*_COLUMNS``).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Optional

import numpy as np
import pandas as pd

from monolib.data.protocols import family
from monolib.methods import METHODS
from monolib.params import PAPER, SIBLINGS
from monolib.report.bootstrap import Bootstrap, paired_difference, rows_of
from monolib.report.results import (
    METRICS, is_image, method_order, metric_cols, natural_key, only_protocol, sort_rows, split_metric, with_protocol
)

# ---- every threshold against its scenario's best, and what the edges cost --------------------------------------

TEST_COLUMNS = ["method", "scenario", "protocol", "metric", "k", "threshold", "best_threshold", "diff", "ci_lo",
                "ci_hi", "significant"]


def best_threshold(means: pd.Series) -> float:
    """The threshold with the highest mean (index: thresholds); ties (to 1e-9): the smallest threshold."""
    top = means.max()
    return float(min(t for t, v in means.items() if v >= top - 1e-9))


def threshold_tests(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap) -> pd.DataFrame:
    """Per (method, scenario, protocol, metric, k) with more than one threshold: every threshold against the
    scenario's best (highest mean; ties: the smallest threshold), paired bootstrap of (threshold - best) on the
    protocol's queries. Columns `TEST_COLUMNS` (significant: the interval excludes 0, i.e. significantly worse
    than the best)."""
    rows = []
    if "protocol" not in iv.columns:
        iv = iv.assign(protocol=PAPER)
    for (method, scenario, protocol), g in iv.groupby(["method", "scenario", "protocol"], sort=False):
        if g["threshold"].nunique() < 2:
            continue
        best = {f"{m}@{k}": best_threshold(gm.set_index("threshold")["mean"])
                for (m, k), gm in g.groupby(["metric", "k"], sort=False)}
        for t in sorted(g["threshold"].unique()):
            for b in sorted(set(best.values()) - {t}):
                cols = [c for c, bt in best.items() if bt == b]
                d = paired_difference(rows_of(qv, method, scenario, t, protocol),
                                      rows_of(qv, method, scenario, b, protocol), boot, cols)
                for r in d.itertuples(index=False):
                    rows.append((method, scenario, protocol, r.metric, int(r.k), float(t), b, r.diff, r.ci_lo,
                                 r.ci_hi, bool(r.significant)))
    out = pd.DataFrame(rows, columns=TEST_COLUMNS)
    out["metric_order"] = out["metric"].map(METRICS.index)
    out = sort_rows(out, ["method", "scenario", "protocol", "metric_order", "k",
                          "threshold"]).drop(columns="metric_order")
    return out


EDGE_PENALTY_COLUMNS = ["method", "scenario", "threshold", "protocol", "metric", "k", "no_edges", "mean", "diff",
                        "ci_lo", "ci_hi", "significant", "n_seeds"]


def edge_penalty(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, k: int = 1,
                 protocol: str = PAPER) -> pd.DataFrame:
    """What the edges cost each encoder: per graph method and scenario with a cell without edges (threshold 0),
    recall@k at every other threshold minus recall@k without edges, a paired bootstrap on the seeds, settings and
    queries the two share (columns `EDGE_PENALTY_COLUMNS`; ``no_edges`` and ``mean``: the two means of
    `monolib.report.bootstrap.intervals`)."""
    rows = []
    col = f"recall@{k}"
    ivp = iv[(iv["metric"] == "recall") & (iv["k"] == k) & (iv.get("protocol", PAPER) == protocol)]
    for (method, scenario), g in ivp.groupby(["method", "scenario"], sort=False):
        means = g.set_index("threshold")["mean"]
        if 0.0 not in means.index or len(means) < 2:
            continue
        base = rows_of(qv, method, scenario, 0.0, protocol)
        for t in sorted(set(means.index) - {0.0}):
            d = paired_difference(rows_of(qv, method, scenario, t, protocol), base, boot, [col])
            for r in d.itertuples(index=False):
                rows.append((method, scenario, float(t), protocol, r.metric, int(r.k), float(means[0.0]),
                             float(means[t]), r.diff, r.ci_lo, r.ci_hi, bool(r.significant), int(r.n_seeds)))
    return pd.DataFrame(rows, columns=EDGE_PENALTY_COLUMNS)


# ---- controlled comparisons: encoder ablation ------------------------------------------------------------------

ABLATION_COLUMNS = ["method", "description", "scenario", "threshold", "protocol", "metric", "k", "mean", "ci_lo",
                    "ci_hi", "n_seeds", "diff_vs_base", "diff_lo", "diff_hi", "significant"]


def _graph_methods(qv: pd.DataFrame, study=None, base: str = "gcn") -> list[str]:
    present = [m for m in method_order(qv["method"].unique())
               if not is_image(m, str(qv.loc[qv["method"] == m, "scenario"].iloc[0]))]
    if study is not None:
        order = [m for m in study.graph_methods() if m in present]
        present = order + [m for m in present if m not in order]
    return ([base] if base in present else []) + [m for m in present if m != base]


def method_description(method: str, study=None) -> str:
    """A method's description: its variant's in the study file, a built-in method's (`METHODS`), else its name."""
    if study is not None and method in getattr(study, "variants", {}):
        return study.variants[method].description or method
    if study is not None and method in METHODS:
        return METHODS[method][1]
    return method


def _pick_cols(cols: list[str]) -> list[str]:
    """recall@1 and precision@6 when present, else the smallest recall k and the largest precision k."""
    rec = sorted((c for c in cols if c.startswith("recall@")), key=lambda c: split_metric(c)[1])
    pre = sorted((c for c in cols if c.startswith("precision@")), key=lambda c: split_metric(c)[1])
    out = []
    if rec:
        out.append("recall@1" if "recall@1" in rec else rec[0])
    if pre:
        out.append("precision@6" if "precision@6" in pre else pre[-1])
    return out


def encoder_ablation(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, study=None,
                     base: str = "gcn", protocol: str = PAPER) -> pd.DataFrame:
    """The encoder variants against `base` on every (scenario, threshold) a variant was run at, on one protocol
    (default ``paper``): recall@1 and precision@6 with their intervals, and the paired bootstrap difference to
    `base` (same seeds, settings and queries). Empty when the study has no variant cells. Columns
    `ABLATION_COLUMNS`."""
    qv, iv = only_protocol(with_protocol(qv), protocol), only_protocol(with_protocol(iv), protocol)
    if qv.empty:
        return pd.DataFrame(columns=ABLATION_COLUMNS)
    methods = _graph_methods(qv, study, base)
    variants = [m for m in methods if m != base]
    if not variants:
        return pd.DataFrame(columns=ABLATION_COLUMNS)
    vq = qv[qv["method"].isin(variants)]
    combos = sorted({(sc, float(t)) for sc, t in zip(vq["scenario"], vq["threshold"])},
                    key=lambda st: (natural_key(st[0]), st[1]))
    cols = _pick_cols(metric_cols(qv))
    ivx = iv.drop(columns="protocol").set_index(["method", "scenario", "threshold", "metric", "k"]).sort_index()
    rows = []
    for m in methods:
        for sc, t in combos:
            mine = rows_of(qv, m, sc, t)
            if mine.empty:
                continue
            diffs = pd.DataFrame()
            if m != base:
                ref = rows_of(qv, base, sc, t)
                if not ref.empty:
                    diffs = paired_difference(mine, ref, boot, cols).set_index(["metric", "k"])
            for c in cols:
                metric, k = split_metric(c)
                key_ = (m, sc, t, metric, k)
                if key_ not in ivx.index:
                    continue
                r = ivx.loc[key_]
                d = diffs.loc[(metric, k)] if (metric, k) in diffs.index else None
                rows.append((m, method_description(m, study), sc, t, protocol, metric, k, float(r["mean"]),
                             float(r["ci_lo"]), float(r["ci_hi"]), int(r["n_seeds"]),
                             *((float(d["diff"]), float(d["ci_lo"]), float(d["ci_hi"]), bool(d["significant"]))
                               if d is not None else (np.nan, np.nan, np.nan, False))))
    return pd.DataFrame(rows, columns=ABLATION_COLUMNS)


# ---- controlled comparisons: dim vs bright settings ------------------------------------------------------------

LIGHT_COLUMNS = ["method", "scenario", "threshold", "protocol", "light", "n_settings", "n_queries", "mean", "ci_lo",
                 "ci_hi", "n_seeds"]


def light_table(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, dim_of: Mapping[str, bool],
                scenarios: Optional[list[str]] = None, method: str = "gcn", k: int = 1,
                protocol: str = PAPER) -> pd.DataFrame:
    """recall@k of the queries of dim and of bright test settings: `method` on each scenario (default: every
    scenario it has) at that scenario's best threshold by mean recall@k (ties: the smallest), and every image
    baseline. Rows ``light`` = dim, bright and ``bright - dim`` (the difference of the two resampled means; the two
    sets of settings are drawn independently, the seeds jointly). One protocol (default ``paper``). Columns
    `LIGHT_COLUMNS`."""
    col = f"recall@{k}"
    qv, iv = only_protocol(with_protocol(qv), protocol), only_protocol(with_protocol(iv), protocol)
    groups = []
    r = iv[(iv["method"] == method) & (iv["metric"] == "recall") & (iv["k"] == k)]
    for sc in sorted(r["scenario"].unique(), key=natural_key):
        if scenarios is not None and sc not in scenarios:
            continue
        groups.append((method, sc, best_threshold(r[r["scenario"] == sc].set_index("threshold")["mean"])))
    for (m, sc, t) in qv[["method", "scenario", "threshold"]].drop_duplicates().itertuples(index=False):
        if is_image(m, sc):
            groups.append((m, sc, float(t)))
    rows = []
    for m, sc, t in groups:
        g = rows_of(qv, m, sc, t)
        if col not in g.columns or g[col].isna().any():
            continue
        dim = g["setting"].map(lambda s: bool(dim_of.get(s, False)))
        parts = {}
        offset = 0
        for light, part in (("dim", g[dim.to_numpy()]), ("bright", g[~dim.to_numpy()])):
            if part.empty:
                rows.append((m, sc, t, protocol, light, 0, 0, np.nan, np.nan, np.nan, 0))
                continue
            values, nq = boot.cube(part, [col])
            off = offset if offset + values.shape[1] <= boot.shape[1] else 0
            iv_ = boot.interval(values, nq, off)
            offset += values.shape[1]
            parts[light] = iv_
            rows.append((m, sc, t, protocol, light, int(part["setting"].nunique()), len(part), float(iv_["mean"][0]),
                         float(iv_["ci_lo"][0]), float(iv_["ci_hi"][0]), int(part["seed"].nunique())))
        if len(parts) == 2:
            d = parts["bright"]["boot"][:, 0] - parts["dim"]["boot"][:, 0]
            lo, hi = np.nanpercentile(d, [2.5, 97.5])
            rows.append((m, sc, t, protocol, "bright - dim", int(g["setting"].nunique()), len(g),
                         float(parts["bright"]["mean"][0] - parts["dim"]["mean"][0]), float(lo), float(hi),
                         int(g["seed"].nunique())))
    return pd.DataFrame(rows, columns=LIGHT_COLUMNS)


# ---- controlled comparisons: depth scale -----------------------------------------------------------------------

DEPTH_COLUMNS = ["method", "depth", "semantic", "scenario", "depth_scale", "threshold", "protocol", "mean", "ci_lo",
                 "ci_hi", "n_seeds", "diff_vs_scale1", "diff_lo", "diff_hi", "significant"]


def depth_scale_table(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, info: pd.DataFrame,
                      method: str = "gcn", k: int = 1, protocol: str = PAPER) -> pd.DataFrame:
    """recall@k against the depth scale factor: the scenarios with ``depth_scale != 1`` and, per (depth,
    semantic) source pair, the scenario with the same sources and scale 1 (the one in the tables first), at
    every threshold `method` was run; with the paired difference to scale 1 at the same threshold. Empty when
    the study has no scaled scenario. One protocol (default ``paper``). `info`: `monolib.report.results.scenario_info`.
    Columns `DEPTH_COLUMNS`."""
    col = f"recall@{k}"
    qv, iv = only_protocol(with_protocol(qv), protocol), only_protocol(with_protocol(iv), protocol)
    rows = []
    if info.empty:
        return pd.DataFrame(columns=DEPTH_COLUMNS)
    scaled = info[info["depth_scale"] != 1.0]
    r = iv[(iv["method"] == method) & (iv["metric"] == "recall") & (iv["k"] == k)]
    for (depth, semantic), grp in scaled.groupby(["depth", "semantic"], sort=False):
        same = info[(info["depth"] == depth) & (info["semantic"] == semantic)
                    & (info["projection"] == grp["projection"].iloc[0])]
        ones = same[same["depth_scale"] == 1.0].sort_values("in_tables", ascending=False, kind="mergesort")
        ref = str(ones["scenario"].iloc[0]) if len(ones) else None
        members = ([ref] if ref else []) + list(grp["scenario"])
        for sc in members:
            scale = float(info.loc[info["scenario"] == sc, "depth_scale"].iloc[0])
            for _, row in r[r["scenario"] == sc].sort_values("threshold").iterrows():
                t = float(row["threshold"])
                d = None
                if ref and sc != ref and not rows_of(qv, method, ref, t).empty:
                    dd = paired_difference(rows_of(qv, method, sc, t), rows_of(qv, method, ref, t), boot, [col])
                    d = dd.iloc[0] if len(dd) else None
                rows.append((method, depth, semantic, sc, scale, t, protocol, float(row["mean"]), float(row["ci_lo"]),
                             float(row["ci_hi"]), int(row["n_seeds"]),
                             *((float(d["diff"]), float(d["ci_lo"]), float(d["ci_hi"]), bool(d["significant"]))
                               if d is not None else (np.nan, np.nan, np.nan, False))))
    out = pd.DataFrame(rows, columns=DEPTH_COLUMNS)
    return out.sort_values(["depth", "semantic", "threshold", "depth_scale"], kind="mergesort").reset_index(drop=True)


# ---- controlled comparisons: twins of a scenario in another camera or colour space --------------------------

TWIN_AXES = ("projection", "colour")  # the scenario properties of the graph stage a twin differs in (one at a time)


def twin_columns(axis: str) -> list[str]:
    """The columns of `twin_table` along `axis`."""
    return ["method", "scenario", axis, "pair", f"pair_{axis}", "threshold", "protocol", "metric", "k", "mean", "ci_lo",
            "ci_hi", "pair_mean", "pair_ci_lo", "pair_ci_hi", "diff", "diff_lo", "diff_hi", "significant", "n_seeds"]


PROJECTION_COLUMNS = twin_columns("projection")
COLOUR_COLUMNS = twin_columns("colour")


def twin_table(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, info: pd.DataFrame, axis: str = "projection",
               k: int = 1, protocol: str = PAPER) -> pd.DataFrame:
    """recall@k of the same method, sources and threshold with the graphs built two ways along `axis` (`TWIN_AXES`:
    the camera of the back-projection, or the space of the node colours): each scenario of the tables (`info`:
    `monolib.report.results.scenario_info`) against every scenario with the same depth, semantics, depth scale and
    the same value on the other axes, but another on `axis` (its `pair`), at every threshold both were run, with
    the paired difference pair - scenario (same seeds, settings and queries). Empty when the study has no such
    pair. Columns `twin_columns(axis)`."""
    col = f"recall@{k}"
    qv, iv = only_protocol(with_protocol(qv), protocol), only_protocol(with_protocol(iv), protocol)
    r = iv[(iv["metric"] == "recall") & (iv["k"] == k)]
    others = [a for a in TWIN_AXES if a != axis and a in info.columns]
    rows = []
    for _, base in info[info["in_tables"].astype(bool)].iterrows():
        same = (info["depth"] == base["depth"]) & (info["semantic"] == base["semantic"]) \
            & (info["depth_scale"] == base["depth_scale"]) & (info[axis] != base[axis])
        for other_axis in others:
            same &= info[other_axis] == base[other_axis]
        for _, twin in info[same].iterrows():
            sc, other = str(base["scenario"]), str(twin["scenario"])
            mine, theirs = r[r["scenario"] == sc], r[r["scenario"] == other]
            for (m, t), a in mine.groupby(["method", "threshold"], sort=False):
                b = theirs[(theirs["method"] == m) & (theirs["threshold"] == t)]
                if b.empty:
                    continue
                a, b = a.iloc[0], b.iloc[0]
                d = paired_difference(rows_of(qv, m, other, t), rows_of(qv, m, sc, t), boot, [col])
                d = d.iloc[0] if len(d) else None
                rows.append((m, sc, str(base[axis]), other, str(twin[axis]), float(t), protocol,
                             "recall", k, float(a["mean"]), float(a["ci_lo"]), float(a["ci_hi"]), float(b["mean"]),
                             float(b["ci_lo"]), float(b["ci_hi"]),
                             *((float(d["diff"]), float(d["ci_lo"]), float(d["ci_hi"]), bool(d["significant"]))
                               if d is not None else (np.nan, np.nan, np.nan, False)),
                             int(min(a["n_seeds"], b["n_seeds"]))))
    out = pd.DataFrame(rows, columns=twin_columns(axis))
    return out.sort_values(["scenario", "method", "threshold"], kind="mergesort").reset_index(drop=True)


def projection_table(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, info: pd.DataFrame, k: int = 1,
                     protocol: str = PAPER) -> pd.DataFrame:
    """`twin_table` along the camera of the back-projection (columns `PROJECTION_COLUMNS`)."""
    return twin_table(qv, iv, boot, info, "projection", k, protocol)


def colour_table(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, info: pd.DataFrame, k: int = 1,
                 protocol: str = PAPER) -> pd.DataFrame:
    """`twin_table` along the space of the node colours (columns `COLOUR_COLUMNS`)."""
    return twin_table(qv, iv, boot, info, "colour", k, protocol)


# ---- controlled comparisons: the two protocols side by side ----------------------------------------------------

PROTOCOLS_COLUMNS = ["method", "scenario", "threshold", "protocol", "metric", "k", "mean", "ci_lo", "ci_hi",
                     "n_seeds", "n_settings", "n_queries"]


def protocols_table(qv: pd.DataFrame, iv: pd.DataFrame, hidden: frozenset | set = frozenset(), k: int = 1,
                    base: str = PAPER) -> pd.DataFrame:
    """recall@k of every method on every protocol, from the same cells: each graph method on each scenario in the
    tables at the threshold with the best mean recall@k of the `base` protocol (ties: the smallest), every image
    method; with the 95 % bootstrap interval of each protocol (its own resample: the two are not paired) and the
    numbers of settings and queries behind it. Columns `PROTOCOLS_COLUMNS`."""
    iv, qv = with_protocol(iv), with_protocol(qv)
    r = iv[(iv["metric"] == "recall") & (iv["k"] == k) & ~iv["scenario"].isin(hidden)]
    groups = []
    for (m, sc), g in r.groupby(["method", "scenario"], sort=False):
        b = g[g["protocol"] == base]
        if b.empty:
            continue
        t = float(b["threshold"].iloc[0]) if is_image(m, sc) else best_threshold(b.set_index("threshold")["mean"])
        groups.append((m, sc, t))
    rows = []
    for m, sc, t in groups:
        for _, x in r[(r["method"] == m) & (r["scenario"] == sc) & (r["threshold"] == t)].iterrows():
            q = rows_of(qv, m, sc, t, x["protocol"])
            n_set = int(q.groupby("seed")["setting"].nunique().max()) if len(q) else 0
            n_q = int(q.groupby("seed").size().max()) if len(q) else 0
            rows.append((m, sc, t, x["protocol"], "recall", k, float(x["mean"]), float(x["ci_lo"]), float(x["ci_hi"]),
                         int(x["n_seeds"]), n_set, n_q))
    out = pd.DataFrame(rows, columns=PROTOCOLS_COLUMNS)
    if out.empty:
        return out
    out["_img"] = [int(is_image(m, sc)) for m, sc in zip(out["method"], out["scenario"])]
    return sort_rows(out, ["_img", "scenario", "method", "protocol"]).drop(columns="_img").reset_index(drop=True)


# ---- which settings the siblings protocol confuses -------------------------------------------------------------

CONFUSION_COLUMNS = ["method", "scenario", "threshold", "protocol", "n_seeds", "queries", "right", "sibling", "other",
                     "share_right", "share_sibling", "share_other", "sibling_share_of_errors"]


def siblings_confusions(rankings: pd.DataFrame, table: pd.DataFrame, protocol: str = SIBLINGS) -> pd.DataFrame:
    """Where the top-1 matches of the `protocol` (default ``siblings``) queries go, per row of the protocols table
    (`table`: `protocols_table`; each method and scenario at the threshold it picked), over all seeds of that row.

    `rankings`: rankings rows with their cell keys (``method, scenario, threshold, seed, protocol`` and
    ``query, query_setting, rank, match, match_setting``; `monolib.report.results.rankings_table`). Each query's
    rank-1 match is ``right`` (its own setting), ``sibling`` (another setting of its family,
    `monolib.data.protocols.family`) or ``other`` (another family). Per row: ``queries`` (over seeds), the three
    counts, their shares in percent and ``sibling_share_of_errors`` = 100 x sibling / (sibling + other) (NaN
    without errors). Rows in the order of `table`; empty (columns `CONFUSION_COLUMNS`) when `table` has no row of
    `protocol`. Columns `CONFUSION_COLUMNS`."""
    keys = ["method", "scenario", "threshold"]
    rows = with_protocol(table)
    rows = rows.loc[rows["protocol"] == protocol, keys].drop_duplicates().reset_index(drop=True)
    if rows.empty or rankings.empty:
        return pd.DataFrame(columns=CONFUSION_COLUMNS)
    top = rankings[(with_protocol(rankings)["protocol"] == protocol) & (rankings["rank"] == 1)]
    top = top.assign(threshold=top["threshold"].astype(float)).merge(
        rows.assign(threshold=rows["threshold"].astype(float), _row=np.arange(len(rows))), on=keys)
    if top.empty:
        return pd.DataFrame(columns=CONFUSION_COLUMNS)
    settings = pd.unique(pd.concat([top["query_setting"], top["match_setting"]]).astype(str))
    fam = pd.Series({s: family(s) for s in settings})           # one call per setting, not per query
    q_set, m_set = top["query_setting"].astype(str), top["match_setting"].astype(str)
    kind = np.select([(m_set == q_set).to_numpy(), (m_set.map(fam) == q_set.map(fam)).to_numpy()],
                     ["right", "sibling"], "other")
    counts = (pd.crosstab(top["_row"], kind).reindex(columns=["right", "sibling", "other"], fill_value=0)
              .astype(int))
    out = rows.iloc[counts.index].reset_index(drop=True)
    out.insert(3, "protocol", protocol)
    out.insert(4, "n_seeds", top.groupby("_row")["seed"].nunique().reindex(counts.index).to_numpy())
    c = counts.reset_index(drop=True)
    out["queries"] = c.sum(axis=1).to_numpy()
    for k in ("right", "sibling", "other"):
        out[k] = c[k].to_numpy()
    for k in ("right", "sibling", "other"):
        out[f"share_{k}"] = 100.0 * out[k] / out["queries"]
    errors = out["sibling"] + out["other"]
    out["sibling_share_of_errors"] = (100.0 * out["sibling"] / errors.where(errors > 0)).astype(float)
    return out[CONFUSION_COLUMNS]
