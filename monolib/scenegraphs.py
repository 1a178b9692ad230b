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

import numpy as np
import torch
from torch_geometric.data import Data
from tqdm.auto import tqdm

from monolib import dataset as dataset_mod
from monolib.graph import NODE_FEATURES, complete_graph, scene_nodes
from monolib.io import DataFileError, atomic_path
from monolib.params import Study, key_of

log = logging.getLogger(__name__)
SPLITS = ("train", "val", "test")


def scenario_key(study: Study, scenario: str) -> str:
    """Cache key of a scenario's graphs: the dataset, the frame selection and the two sources' model keys."""
    from monolib import perception

    sc = study.scenarios[scenario]
    sources = {}
    for role, name in (("depth", sc.depth), ("semantic", sc.semantic)):
        sources[role] = "gt" if name == "gt" else perception.model_key(study, name)
    return key_of({"dataset": study.dataset, "graphs_root": study.graphs_root, "seed": study.seed,
                   "protocol": study.protocol, "val": study.gcn.val_settings, "sources": sources,
                   "depth_scale": sc.depth_scale, "version": 1})


def graphs_path(study: Study, scenario: str) -> Path:
    return study.data_dir / "graphs" / f"{scenario}-{scenario_key(study, scenario)}.pt"


_OPEN: dict = {}


def _frame_nodes(args) -> list[tuple[np.ndarray, np.ndarray]]:
    """Worker: the nodes of one frame for each scenario, reading every source once."""
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
            cache[(kind, name)] = read(f)
        return cache[(kind, name)]

    out = []
    for sc_name in scenarios:
        sc = study.scenarios[sc_name]
        try:
            depth = source("depth", sc.depth) * np.float32(sc.depth_scale)
            out.append(scene_nodes(f.rgb, depth, source("semantic", sc.semantic), f.camera))
        except (DataFileError, FileNotFoundError) as exc:  # a missing Hypersim file: an empty graph, reported
            out.append((np.zeros((0, NODE_FEATURES), np.float32), np.zeros((0, 3), np.float32), str(exc)))
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
    if study.graphs_root:
        from monolib import published

        graphs = published.select(study)
        built = {sc: graphs for sc in todo}
    else:
        ds = dataset_mod.open_dataset(study)
        sel = dataset_mod.select_frames(study, ds, study.gcn.val_settings)
        frames = [(split, f) for split in SPLITS for f in getattr(sel, split)]
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
            missing = []
            for (split, f), per_scenario in zip(frames, nodes):
                x, pos, *error = per_scenario[i]
                missing += error
                built[sc][split].append(complete_graph(x, pos, f.setting, f.key))
            if missing:
                log.warning("graphs: %s: %d frames with a missing or unreadable file became empty graphs "
                            "(first: %s)", sc, len(missing), missing[0])
    seconds = time.perf_counter() - t0
    for sc in todo:
        with atomic_path(out[sc]) as tmp:
            torch.save({"scenario": sc, "graphs": built[sc], "seconds": seconds}, tmp)
        n = sum(len(v) for v in built[sc].values())
        log.info("graphs: %s built, %d graphs (%d scenarios in %.1f s)", sc, n, len(todo), seconds)
    return out


def load(study: Study, scenario: str, progress: bool = False) -> dict[str, list[Data]]:
    """{'train': [...], 'val': [...], 'test': [...]} complete graphs of a scenario (built when missing)."""
    return torch.load(build(study, scenario, progress), weights_only=False)["graphs"]
