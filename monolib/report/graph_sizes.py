"""Graph sizes per scenario and threshold (what a threshold changes): ``graph_sizes.csv`` and ``graph_sizes.md``,
from the graph stage's files of the scenarios and thresholds of the study's grid."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from monolib import methods, paths
from monolib.graphs.build import pair_mask
from monolib.graphs.scenegraphs import identical_thresholds, load_file
from monolib.io import write_text
from monolib.params import Study
from monolib.report.tables import threshold_label
from monolib.retrieval.grid import grid

SIZE_COLUMNS = ["scenario", "label", "threshold", "test_graphs", "test_nodes", "test_edges", "test_empty",
                "train_graphs", "train_nodes", "train_edges", "same_graphs_as", "missing_frames",
                "dropped_pixels", "frames_with_dropped_pixels"]


def _scenario_thresholds(study: Study) -> dict[str, list[float]]:
    """The thresholds each scenario's graph cells run at (every graph method of the grid)."""
    out: dict[str, set] = {}
    for c in grid(study):
        if methods.kind(c.method, study) == "graph":
            out.setdefault(c.scenario, set()).add(float(c.threshold))
    return {sc: sorted(out[sc]) for sc in study.scenarios if sc in out}


def graph_sizes(study: Study) -> pd.DataFrame:
    """Nodes and edges per graph for each scenario and threshold of the study's grid: means over the test split's
    graphs and over the training split's (training + validation settings); edges = node pairs joined (the paper's
    encoder reads each once, from the lower NYU40 id to the higher; the undirected encoders both ways); ``test_empty``:
    test graphs without a node; ``missing_frames``: frames of the scenario (all splits) with a missing or unreadable
    dataset file, each an empty graph; ``dropped_pixels``: labelled pixels per frame (mean over all splits) left out of
    the nodes for their depth (NaN, inf or <= 0), ``frames_with_dropped_pixels``: the frames with any (NaN and -1 for
    graphs that were not built here: published graphs); ``same_graphs_as``: the smallest threshold whose graphs (every
    split) are identical (`identical_thresholds`; NaN when none). Columns `SIZE_COLUMNS`."""
    rows = []
    for sc, thresholds in _scenario_thresholds(study).items():
        data = load_file(study, sc)
        graphs = data["graphs"]
        parts = {"test": graphs["test"], "train": graphs["train"] + graphs["val"]}
        lengths = {k: torch.cat([g.pair_len for g in v] + [torch.zeros(0)]) for k, v in parts.items()}
        same = identical_thresholds(torch.cat(list(lengths.values())), thresholds)
        label = study.scenarios[sc].label or sc
        for t in thresholds:
            row = {"scenario": sc, "label": label, "threshold": t}
            for k, v in parts.items():
                n = max(len(v), 1)
                row[f"{k}_graphs"] = len(v)
                row[f"{k}_nodes"] = float(sum(int(g.num_nodes) for g in v)) / n
                row[f"{k}_edges"] = float(pair_mask(lengths[k], t).sum()) / n
            row["test_empty"] = int(sum(int(g.num_nodes) == 0 for g in parts["test"]))
            row["same_graphs_as"] = same.get(t, float("nan"))
            row["missing_frames"] = len(data.get("missing", []))
            per_frame = [n for split in (data.get("dropped_pixels") or {}).values() for n in split]
            row["dropped_pixels"] = float(np.mean(per_frame)) if per_frame else float("nan")
            row["frames_with_dropped_pixels"] = int(sum(n > 0 for n in per_frame)) if per_frame else -1
            rows.append(row)
    return pd.DataFrame(rows, columns=SIZE_COLUMNS)


def graph_sizes_markdown(table: pd.DataFrame) -> str:
    """``graph_sizes.md``: the table of `graph_sizes` for a reader."""
    lines = ["**Graph sizes.** Nodes and edges per scene graph for each scenario and edge threshold: means over the "
             "test split's graphs and over the training split's (training and validation settings). An edge is a node "
             "pair closer than the threshold (the paper's encoder reads it once, from the node of lower NYU40 id "
             "to the higher; `ours`, `layout` and the undirected ablations both ways); 0: no edges, the encoder sees "
             "the nodes only; ∞: every pair. *Same graphs as*: a smaller threshold whose graphs are identical in every "
             "frame of every split (no node pair has a length between the two): the study copies that threshold's "
             "cells, so the threshold changes nothing.", "",
             "| scenario | threshold (m) | nodes / graph (test) | edges / graph (test) | nodes / graph (train) "
             "| edges / graph (train) | same graphs as |",
             "|---|---|---:|---:|---:|---:|---|"]
    prev = None
    for r in table.itertuples(index=False):
        first = r.scenario != prev
        prev = r.scenario
        same = "" if pd.isna(r.same_graphs_as) else threshold_label(float(r.same_graphs_as))
        lines.append(f"| {f'{r.scenario}: {r.label}' if first else ''} | {threshold_label(float(r.threshold))} | "
                     f"{r.test_nodes:.2f} | {r.test_edges:.2f} | {r.train_nodes:.2f} | {r.train_edges:.2f} | {same} |")
    if "dropped_pixels" in table and table["dropped_pixels"].notna().any():  # said, never silent
        per = table.groupby("scenario", sort=False)[["dropped_pixels", "frames_with_dropped_pixels"]].first().dropna()
        frames = int(table.groupby("scenario", sort=False)["test_graphs"].first().iloc[0]
                     + table.groupby("scenario", sort=False)["train_graphs"].first().iloc[0])
        lines += ["", f"**Labelled pixels left out for their depth** (NaN, inf or <= 0; per frame, mean over the "
                  f"{frames} frames of all splits, and the frames with any): " +
                  ", ".join(f"{sc} {r.dropped_pixels:.1f} ({int(r.frames_with_dropped_pixels)} frames)"
                            for sc, r in per.iterrows()) + "."]
    missing = table.groupby("scenario", sort=False)["missing_frames"].max() if "missing_frames" in table else None
    if missing is not None and missing.sum() > 0:  # a real download with files missing: said, never silent
        lines += ["", "**Frames with a missing or unreadable file of the dataset** (each is an empty graph in every "
                  "threshold): " + ", ".join(f"{sc} {int(n)}" for sc, n in missing.items()) + "."]
    return "\n".join(lines) + "\n"


def write_graph_sizes(study: Study, out_dir: Path | None = None) -> dict[str, Path]:
    """Write ``graph_sizes.csv`` and ``graph_sizes.md`` (`graph_sizes`) into `out_dir` (default: the study's
    figures folder, `monolib.paths.figures_dir`); nothing when the study has no graph method."""
    table = graph_sizes(study)
    if table.empty:
        return {}
    out = Path(out_dir) if out_dir is not None else paths.figures_dir(study.name)
    csv = table.copy()
    csv["threshold"] = csv["threshold"].map(paths.threshold_tag)
    csv["same_graphs_as"] = [("" if pd.isna(t) else paths.threshold_tag(t)) for t in csv["same_graphs_as"]]
    write_text(out / "graph_sizes.csv", csv.to_csv(index=False, float_format="%.4g", lineterminator="\n"))
    write_text(out / "graph_sizes.md", graph_sizes_markdown(table))
    return {"graph_sizes_csv": out / "graph_sizes.csv", "graph_sizes_md": out / "graph_sizes.md"}
