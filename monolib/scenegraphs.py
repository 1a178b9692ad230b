"""The graph stage: one complete scene graph per selected frame and scenario, cached on disk.

A cached graph holds its nodes (`x`, and `pos` when built from depth) and every node pair i < j with its length
(`pair_index`, `pair_len`). A threshold then only filters pairs (`monolib.graph.at_threshold`), so the five thresholds of the
ablation share one build, and published graph files (lengths without positions) fit the same format.
"""
from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd
import torch
from torch_geometric.data import Data
from monolib.progress import tqdm

from monolib import dataset as dataset_mod
from monolib.graph import NODE_FEATURES, complete_graph, scene_nodes
from monolib.io import DataFileError, load_cached, save_torch
from monolib.params import Study, key_of, resolve_path

log = logging.getLogger(__name__)
SPLITS = ("train", "val", "test")


def scenario_key(study: Study, scenario: str) -> str:
    """Cache key of a scenario's graphs: the dataset's key, the frame selection, the two sources' model keys and
    the version of the graph code (`monolib.versions`)."""
    from monolib import perception

    sc = study.scenarios[scenario]
    sources = {}
    for role, name in (("depth", sc.depth), ("semantic", sc.semantic)):
        sources[role] = "gt" if name == "gt" else perception.model_key(study, name)
    from monolib.dataset import dataset_key
    from monolib.versions import code_version, library_versions

    pr = study.protocol  # what chooses the frames (not the k of the metrics, nor the queries' draw)
    return key_of({"dataset": dataset_key(study), "published": published_fingerprint(study), "seed": study.seed,
                   "frames": {"settings": pr.settings, "siblings": pr.siblings, "families": pr.families,
                              "frames": pr.frames},
                   "val": study.gcn.val_settings, "sources": sources, "depth_scale": sc.depth_scale,
                   "code": code_version("graphs"), "libraries": library_versions("graphs")})


def published_fingerprint(study: Study) -> Optional[str]:
    """The published graph files of a study (`graphs_root`) by name and size, not by where they are."""
    if not study.graphs_root:
        return None
    import hashlib

    root = resolve_path(study.graphs_root, study.path)
    files = sorted(f"{p.relative_to(root)}:{p.stat().st_size}" for p in root.glob("*/*_graphs.pt"))
    return hashlib.sha256("\n".join(files).encode()).hexdigest()[:16]


def graphs_path(study: Study, scenario: str) -> Path:
    return study.data_dir / "graphs" / f"{scenario}-{scenario_key(study, scenario)}.pt"


_OPEN: dict = {}


def _frame_nodes(args) -> list[tuple]:
    """Worker: per scenario, the nodes of one frame ``(x, pos, dropped pixels[, error])``, reading every source
    once; `dropped pixels`: labelled pixels left out for their depth (NaN, inf, <= 0)."""
    study, scenarios, key = args
    from monolib import perception

    root = str(study.dataset_root)
    if root not in _OPEN:  # one index per worker process, not one per frame
        _OPEN[root] = dataset_mod.open_dataset(study)
    f = _OPEN[root].frame_by_key(key)
    cache: dict = {}

    def source(kind: str, name: str):
        if (kind, name) not in cache:
            read = perception.depth_source(study, name) if kind == "depth" else perception.semantic_source(study, name)
            cache[(kind, name)] = read(f)  # a model's missing prediction raises PredictionsMissing
        return cache[(kind, name)]

    out = []
    for sc_name in scenarios:
        sc = study.scenarios[sc_name]
        try:
            depth = source("depth", sc.depth) * np.float32(sc.depth_scale)
            semantic = source("semantic", sc.semantic)
            x, pos = scene_nodes(f.rgb, depth, semantic, f.camera)
            with np.errstate(invalid="ignore"):  # labelled pixels left out for their depth (NaN, inf, <= 0)
                dropped = int(np.count_nonzero((np.asarray(semantic) >= 1) & ~(np.isfinite(depth) & (depth > 0))))
            out.append((x, pos, dropped))
        except perception.PredictionsMissing:  # a model's prediction: never an empty graph
            raise
        except (DataFileError, FileNotFoundError) as exc:  # a missing file of the download: an empty graph, counted
            out.append((np.zeros((0, NODE_FEATURES), np.float32), np.zeros((0, 3), np.float32), 0, str(exc)))
    return out


def build(study: Study, scenario: str, progress: bool = True) -> Path:
    """Build (or find cached) the graphs of every selected frame for one scenario."""
    return build_all(study, [scenario], progress)[scenario]


def build_all(study: Study, scenarios: list[str], progress: bool = True) -> dict[str, Path]:
    """Build the graphs of several scenarios in one pass over the frames (each file read once), in
    `dataset.workers` processes; scenarios already cached are skipped."""
    out = {sc: graphs_path(study, sc) for sc in scenarios}
    todo = [sc for sc in scenarios if not out[sc].exists()]
    for sc in scenarios:
        if sc not in todo:
            log.info("graphs: %s cached (%s)", sc, out[sc].name)
    if not todo:
        return out
    t0 = time.perf_counter()
    missing: dict[str, list[str]] = {}
    dropped: dict[str, dict[str, list[int]]] = {}  # labelled pixels left out for their depth, per frame
    if study.graphs_root:
        from monolib import published

        graphs = published.select(study)
        built = {sc: graphs for sc in todo}
    else:
        from monolib import perception

        ds = dataset_mod.open_dataset(study)
        sel = dataset_mod.select_frames(study, ds, study.gcn.val_settings)
        frames = [(split, f) for split in SPLITS for f in getattr(sel, split)]
        for sc in todo:  # fail before any work when a model has not predicted these frames
            for name in {study.scenarios[sc].depth, study.scenarios[sc].semantic} - {"gt"}:
                perception.check_predictions(study, name, [f for _, f in frames])
        jobs = [(study, todo, f.key) for _, f in frames]
        workers = max(1, min(study.dataset.workers, os.cpu_count() or 1))
        if workers > 1:
            import multiprocessing as mp

            with mp.get_context("fork").Pool(workers) as pool:
                nodes = list(tqdm(pool.imap(_frame_nodes, jobs, chunksize=8), total=len(jobs),
                                  desc=f"graphs {'+'.join(todo)}", disable=not progress, leave=False))
        else:
            nodes = [_frame_nodes(j) for j in tqdm(jobs, desc=f"graphs {'+'.join(todo)}", disable=not progress, leave=False)]
        built = {}
        for i, sc in enumerate(todo):
            built[sc] = {split: [] for split in SPLITS}
            missing[sc], dropped[sc] = [], {split: [] for split in SPLITS}
            for (split, f), per_scenario in zip(frames, nodes):
                x, pos, n_dropped, *error = per_scenario[i]
                missing[sc] += [f"{f.key}: {e}" for e in error]
                dropped[sc][split].append(n_dropped)
                built[sc][split].append(complete_graph(x, pos, f.setting, f.key))
            if missing[sc]:
                print(f"graphs: {sc}: {len(missing[sc])} frames have a missing or unreadable file of the dataset and "
                      f"are empty graphs (counted in graph_sizes.md; first: {missing[sc][0]})", flush=True)
    seconds = time.perf_counter() - t0
    for sc in todo:
        save_torch(out[sc], {"scenario": sc, "graphs": built[sc], "missing": missing.get(sc, []), "seconds": seconds,
                             "dropped_pixels": dropped.get(sc)})
        n = sum(len(v) for v in built[sc].values())
        log.info("graphs: %s built, %d graphs (%d scenarios in %.1f s)", sc, n, len(todo), seconds)
    return out


def _read_graphs(path: Path) -> dict:
    data = torch.load(path, weights_only=False)
    if not isinstance(data, dict) or not isinstance(data.get("graphs"), dict) or set(data["graphs"]) != set(SPLITS):
        raise ValueError(f"expected {{'graphs': {{{', '.join(SPLITS)}}}}}")
    return data


def load_file(study: Study, scenario: str, progress: bool = False) -> dict:
    """The cached graphs file of a scenario (`graphs` per split, `missing` frames, `seconds`), built when absent;
    an unreadable file (cut short) is removed with a warning and built again (`monolib.io.load_cached`)."""
    path = graphs_path(study, scenario)
    data = load_cached(path, _read_graphs, f"graphs file of scenario {scenario}")
    if data is None:
        build(study, scenario, progress)
        data = _read_graphs(path)
    return data


def load(study: Study, scenario: str, progress: bool = False) -> dict[str, list[Data]]:
    """{'train': [...], 'val': [...], 'test': [...]} complete graphs of a scenario (built when missing)."""
    return load_file(study, scenario, progress)["graphs"]


# ---- graph sizes per scenario and threshold (what a threshold changes) ----------------------------------------

SIZE_COLUMNS = ["scenario", "label", "threshold", "test_graphs", "test_nodes", "test_edges", "test_empty",
                "train_graphs", "train_nodes", "train_edges", "same_graphs_as", "missing_frames",
                "dropped_pixels", "frames_with_dropped_pixels"]


def identical_thresholds(pair_len: torch.Tensor, thresholds) -> dict[float, float]:
    """``{threshold: the smallest threshold with identical graphs}`` for the thresholds whose graphs equal those of
    a smaller one: no node pair (of `pair_len`, every pair of every graph) has a length between the two. Edges only
    grow with the threshold, so equal edge totals mean equal graphs: the rule of `monolib.study.same_graphs`."""
    from monolib.graph import pair_mask

    out: dict[float, float] = {}
    source, source_edges = None, -1
    for t in sorted(set(float(t) for t in thresholds)):
        edges = int(pair_mask(pair_len, t).sum())
        if edges == source_edges:
            out[t] = source
        else:
            source, source_edges = t, edges
    return out


def _scenario_thresholds(study: Study) -> dict[str, list[float]]:
    """The thresholds each scenario's graph cells run at (every graph method of the grid)."""
    from monolib import methods
    from monolib.grid import grid

    out: dict[str, set] = {}
    for c in grid(study):
        if methods.kind(c.method, study) == "graph":
            out.setdefault(c.scenario, set()).add(float(c.threshold))
    return {sc: sorted(out[sc]) for sc in study.scenarios if sc in out}


def graph_sizes(study: Study) -> pd.DataFrame:
    """Nodes and edges per graph for each scenario and threshold of the study's grid: means over the test split's
    graphs and over the training split's (training + validation settings); edges = node pairs joined (the encoder
    reads each in both directions); ``test_empty``: test graphs without a node; ``missing_frames``: frames of the scenario (all splits) with a
    missing or unreadable dataset file, each an empty graph; ``dropped_pixels``: labelled pixels per frame (mean
    over all splits) left out of the nodes for their depth (NaN, inf or <= 0), ``frames_with_dropped_pixels``: the
    frames with any (NaN and -1 for graphs that were not built here: published graphs); ``same_graphs_as``: the smallest
    threshold whose graphs (every split) are identical (`identical_thresholds`; NaN when none). Columns
    `SIZE_COLUMNS`."""
    from monolib.graph import pair_mask

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
    from monolib.tables import threshold_label

    lines = ["**Graph sizes.** Nodes and edges per scene graph for each scenario and edge threshold: means over the "
             "test split's graphs and over the training split's (training and validation settings). An edge is a node "
             "pair closer than the threshold (the encoder reads it in both directions); 0: no edges, the encoder sees "
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
    from monolib import paths
    from monolib.io import write_text

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
