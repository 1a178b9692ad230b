"""Why the direction of the edges decides: the paper's encoder (`gcn`, each edge pointing from the node of lower
NYU40 id to the higher one) beside its variants that turn the edges round, point them along another node order or
make them undirected, with where each encoder's max-pooled embedding comes from (the share of its entries that the
first node in its order gives: the node that hears nobody when edges point forward).

`write` makes ``direction.{md,csv}`` for a study whose variants of `gcn` (``ablation_of: gcn``) change ``edges`` or
``node_order``; it loads each cell's trained encoder (``model.pt``) and embeds the scenario's test graphs again.
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd
import torch

from monolib import io, paths
from monolib.graphs import scenegraphs
from monolib.params import PAPER
from monolib.report import comparisons
from monolib.report.tables import csv_text, fmt_ci, threshold_label
from monolib.retrieval import gcn

BASE = "gcn"
DIRECTION_KEYS = ("edges", "node_order")  # the encoder choices that decide which node hears which
COLUMNS = ["method", "description", "scenario", "threshold", "recall", "ci_lo", "ci_hi", "first_share",
           "uniform_share", "first_label", "seeds"]


def methods_of(study) -> list[str]:
    """`gcn` and the variants of it that change its edges' direction or its node order (with the other ablations of
    `gcn` that change neither, as controls: the linear head), in the study file's order; [] when none changes the
    direction."""
    variants = {n: v for n, v in (getattr(study, "variants", None) or {}).items() if v.ablation_of == BASE}
    if not any(set(v.gcn) & set(DIRECTION_KEYS) for v in variants.values()):
        return []
    return [BASE, *variants]


def first_node_row(study, method: str, scenario: str, threshold: float, graphs: list) -> dict:
    """`gcn.first_node_share` of each of the study's seeds' trained encoders of one cell group, averaged (the most
    common first label over seeds); seeds whose cell is missing are left out."""
    spec = study.gcn_spec(method)
    test = [gcn.encoder_graph(g, threshold, spec, study.projection(scenario)) for g in graphs]
    shares = []
    for seed in study.seeds:
        state = paths.cell_dir(study.name, method, scenario, threshold, seed, study.fold) / "model.pt"
        if not state.is_file():
            continue
        model = gcn.GraphEncoder(spec)
        model.load_state_dict(torch.load(state, map_location="cpu", weights_only=True))
        shares.append(gcn.first_node_share(model, test))
    if not shares:
        return {"first_share": np.nan, "uniform_share": np.nan, "first_label": -1, "seeds": 0}
    labels = [s["first_label"] for s in shares]
    return {"first_share": float(np.mean([s["share"] for s in shares])), "uniform_share": shares[0]["uniform"],
            "first_label": max(set(labels), key=labels.count), "seeds": len(shares)}


def direction_table(study, iv: pd.DataFrame) -> pd.DataFrame:
    """One row per method of `methods_of` and (scenario, threshold > 0) of its cells: recall@1 on `paper` with its
    interval (`iv`: `monolib.report.bootstrap.intervals`) and `first_node_row`."""
    methods = methods_of(study)
    ivp = iv[(iv["metric"] == "recall") & (iv["k"] == 1) & (iv["protocol"] == PAPER) & iv["method"].isin(methods)]
    rows, graphs = [], {}
    for m in methods:
        for sc, ts in study.cell_thresholds(m).items():
            for t in ts:
                hit = ivp[(ivp["method"] == m) & (ivp["scenario"] == sc) & (ivp["threshold"] == float(t))]
                if t == 0 or hit.empty:
                    continue
                if sc not in graphs:
                    graphs[sc] = scenegraphs.load(study, sc)["test"]
                r = hit.iloc[0]
                rows.append({"method": m, "description": comparisons.method_description(m, study), "scenario": sc,
                             "threshold": float(t),
                             "recall": float(r["mean"]), "ci_lo": float(r["ci_lo"]), "ci_hi": float(r["ci_hi"]),
                             **first_node_row(study, m, sc, float(t), graphs[sc])})
    return pd.DataFrame(rows, columns=COLUMNS)


def direction_markdown(table: pd.DataFrame, labels: Optional[Mapping[str, str]] = None) -> str:
    """``direction.md``: per scenario, a row per method and threshold."""
    labels = dict(labels or {})
    out = ["**Why the direction decides.** Recall@1 on `paper` [95% bootstrap interval] of the paper's encoder "
           "(`gcn`: each edge from the node of lower NYU40 id to the higher one, so that a node hears only the nodes "
           "before it and the first hears nobody) beside the same encoder with its edges along another node order, "
           "undirected, or with a linear head. First node's share: of the 64 max-pooled entries of a test graph, the "
           "share the first node in the encoder's order gives (ties count for it), mean over test graphs of two "
           "nodes or more and over seeds; if every node were as likely: the mean of 1 / nodes. First label: the "
           "NYU40 id most often first.", ""]
    for sc, g in table.groupby("scenario", sort=False):
        out += [f"{sc}: {labels.get(sc, sc)}", "",
                "| method | threshold (m) | recall@1 | first node's share | if every node were as likely | "
                "first label |", "|---|---|---:|---:|---:|---:|"]
        for r in g.itertuples(index=False):
            out.append(f"| `{r.method}` | {threshold_label(r.threshold)} | {r.recall:.1f} "
                       f"{fmt_ci(r.ci_lo, r.ci_hi)} | {r.first_share:.2f} | {r.uniform_share:.2f} | "
                       f"{r.first_label} |")
        out.append("")
    out += ["Methods:"] + [f"- `{m}`: {d}" for m, d in dict(zip(table["method"], table["description"])).items()]
    return "\n".join(out) + "\n"


def write(study, out: Path, iv: Optional[pd.DataFrame], labels: Optional[Mapping[str, str]] = None) -> dict[str, Path]:
    """``direction.{md,csv}`` in `out` when the study has direction variants of `gcn` (else nothing)."""
    if study is None or iv is None or not methods_of(study):
        return {}
    table = direction_table(study, iv)
    if table.empty:
        return {}
    io.write_text(out / "direction.md", direction_markdown(table, labels))
    io.write_text(out / "direction.csv", csv_text(table))
    return {"direction_md": out / "direction.md", "direction_csv": out / "direction.csv"}
