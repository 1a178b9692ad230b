"""The graph stage: one complete scene graph per selected frame and scenario, cached on disk.

A cached graph holds its nodes (`x`, and `pos` when built from depth) and every node pair i < j with its length
(`pair_index`, `pair_len`). A threshold then only filters pairs (`monolib.graphs.build.at_threshold`), so the five
thresholds of the ablation share one build, and published graph files (lengths without positions) fit the same format.
"""
from __future__ import annotations

import logging
import os
import time
from collections import OrderedDict
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from torch_geometric.data import Data

from monolib import versions
from monolib.data import dataset, selection
from monolib.data.hypersim import HdrMissing
from monolib.graphs import published
from monolib.graphs.build import NODE_FEATURES, complete_graph, frame_nodes, pair_mask
from monolib.io import DataFileError, load_cached, save_torch
from monolib.params import Study, key_of, resolve_path
from monolib.perception import predictions
from monolib.progress import tqdm

log = logging.getLogger(__name__)
SPLITS = ("train", "val", "test")


def scenario_keys(study: Study, dataset_key: Optional[str] = None) -> dict[str, str]:
    """The graph stage's key of every scenario of the study (`scenario_key`), the data stage's key and each
    model's key (`monolib.perception.predictions.model_key`) computed once and passed on."""
    data_key = dataset_key if dataset_key is not None else dataset.dataset_key(study)
    used = sorted({n for sc in study.scenarios.values() for n in (sc.depth, sc.semantic)} - {"gt"})
    models = {n: predictions.model_key(study, n, data_key) for n in used}
    return {sc: scenario_key(study, sc, data_key, models) for sc in study.scenarios}


def scenario_key(study: Study, scenario: str, dataset_key: Optional[str] = None,
                 model_keys: Optional[dict[str, str]] = None) -> str:
    """Cache key of a scenario's graphs: the data stage's key, the frame selection, the two sources' model keys
    (the perception stage's), the depth scale, the back-projection (`Study.projection`), the node colours
    (`Study.colour`), the fold of a study with folds by volume (`Study.at_fold`) and the version of the graph code
    and libraries (`monolib.versions`). `dataset_key`, `model_keys`: the upstream stages' keys, when the
    caller holds them (`scenario_keys`); computed here otherwise."""
    sc = study.scenarios[scenario]
    data_key = dataset_key if dataset_key is not None else dataset.dataset_key(study)
    models = model_keys or {}
    sources = {}
    for role, name in (("depth", sc.depth), ("semantic", sc.semantic)):
        sources[role] = "gt" if name == "gt" else models.get(name) or predictions.model_key(study, name, data_key)
    pr = study.protocol  # what chooses the frames (not the k of the metrics, nor the queries' draw)
    return key_of({**study.fold_key(), "dataset": data_key, "published": published_fingerprint(study),
                   "seed": study.seed,
                   "frames": {"settings": pr.settings, "siblings": pr.siblings, "families": pr.families,
                              "frames": pr.frames},
                   "val": study.gcn.val_settings, "sources": sources, "depth_scale": sc.depth_scale,
                   "projection": study.projection(scenario), "colour": study.colour(scenario),
                   "code": versions.code_version("graphs"), "libraries": versions.library_versions("graphs")})


def published_fingerprint(study: Study) -> Optional[str]:
    """The published graph files of a study (`graphs_root`) by name and size, not by where they are."""
    if not study.graphs_root:
        return None
    root = resolve_path(study.graphs_root)
    return key_of(sorted(f"{p.relative_to(root)}:{p.stat().st_size}" for p in root.glob("*/*_graphs.pt")))


def graphs_path(study: Study, scenario: str, key: Optional[str] = None) -> Path:
    """The graphs file of a scenario: ``graphs/<scenario>-<key>.pt`` (`key`: its `scenario_key`, when known)."""
    return study.data_dir / "graphs" / f"{scenario}-{key or scenario_key(study, scenario)}.pt"


_OPEN: dict = {}


def frame_of(study: Study, key: str):
    """The frame `key` of the study's dataset, from one index per process (the workers of `map_frames`)."""
    root = str(study.dataset_root)
    if root not in _OPEN:  # one index per worker process, not one per frame
        _OPEN[root] = dataset.open_dataset(study)
    return _OPEN[root].frame_by_key(key)


def map_frames(work, jobs: list, workers: int, desc: str, progress: bool = True) -> list:
    """``[work(job) for job in jobs]`` in `workers` forked processes (at most the CPUs), in order, with progress."""
    workers = max(1, min(workers, os.cpu_count() or 1))
    if workers > 1:
        import multiprocessing as mp

        with mp.get_context("fork").Pool(workers) as pool:
            return list(tqdm(pool.imap(work, jobs, chunksize=8), total=len(jobs), desc=desc, disable=not progress,
                             leave=False))
    return [work(j) for j in tqdm(jobs, desc=desc, disable=not progress, leave=False)]


def _frame_nodes(args) -> list[tuple]:
    """Worker: per scenario, the nodes of one frame ``(x, pos, dropped pixels[, error])``, reading every source
    once; `dropped pixels`: labelled pixels left out for their depth (NaN, inf, <= 0)."""
    study, scenarios, key = args
    f = frame_of(study, key)
    cache: dict = {}

    def source(kind: str, name: str):
        if (kind, name) not in cache:
            read = (predictions.depth_source if kind == "depth" else predictions.semantic_source)(study, name)
            cache[(kind, name)] = read(f)  # a model's missing prediction raises PredictionsMissing
        return cache[(kind, name)]

    out = []
    for sc_name in scenarios:
        sc = study.scenarios[sc_name]
        try:
            depth = source("depth", sc.depth) * np.float32(sc.depth_scale)
            semantic = source("semantic", sc.semantic)
            colour = f.hdr if study.colour(sc_name) == "hdr" else f.rgb
            out.append(frame_nodes(colour, depth, semantic, f.camera, study.projection(sc_name)))  # (x, pos, left out)
        except (predictions.PredictionsMissing, HdrMissing):  # a model's prediction, HDR colour: never an empty graph
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
    keys = scenario_keys(study)
    out = {sc: graphs_path(study, sc, keys[sc]) for sc in scenarios}
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
        graphs = published.select(study)
        built = {sc: graphs for sc in todo}
    else:
        ds = dataset.open_dataset(study)
        sel = selection.select_frames(study, ds, study.gcn.val_settings)
        frames = [(split, f) for split in SPLITS for f in getattr(sel, split)]
        for sc in todo:  # fail before any work when a model has not predicted these frames
            for name in {study.scenarios[sc].depth, study.scenarios[sc].semantic} - {"gt"}:
                predictions.check_predictions(study, name, [f for _, f in frames])
        jobs = [(study, todo, f.key) for _, f in frames]
        nodes = map_frames(_frame_nodes, jobs, study.dataset.workers, f"graphs {'+'.join(todo)}", progress)
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
        save_torch(out[sc], {"scenario": sc, "projection": study.projection(sc), "graphs": built[sc],
                             "missing": missing.get(sc, []), "seconds": seconds, "dropped_pixels": dropped.get(sc)})
        n = sum(len(v) for v in built[sc].values())
        log.info("graphs: %s built, %d graphs (%d scenarios in %.1f s)", sc, n, len(todo), seconds)
    return out


# Graphs files read in this process, by (path, inode, mtime, size): the cells a warm kernel runs one after another
# read their scenario's file once (the grid runs a scenario's cells in a row), not once per cell. A rebuilt file is a
# new inode (atomic rename), so it is read again. Callers never modify what they get.
_READ: "OrderedDict[tuple, dict]" = OrderedDict()
READ_FILES = 4


def _read_graphs(path: Path) -> dict:
    st = Path(path).stat()
    token = (str(path), st.st_ino, st.st_mtime_ns, st.st_size)
    if token in _READ:
        _READ.move_to_end(token)
        return _READ[token]
    data = torch.load(path, weights_only=False)
    if not isinstance(data, dict) or not isinstance(data.get("graphs"), dict) or set(data["graphs"]) != set(SPLITS):
        raise ValueError(f"expected {{'graphs': {{{', '.join(SPLITS)}}}}}")
    _READ[token] = data
    while len(_READ) > READ_FILES:
        _READ.popitem(last=False)
    return data


def load_file(study: Study, scenario: str, progress: bool = False, key: Optional[str] = None) -> dict:
    """The cached graphs file of a scenario (`graphs` per split, `missing` frames, `seconds`), built when absent;
    an unreadable file (cut short) is removed with a warning and built again (`monolib.io.load_cached`). `key`:
    the scenario's `scenario_key`, when the caller holds it."""
    path = graphs_path(study, scenario, key)
    data = load_cached(path, _read_graphs, f"graphs file of scenario {scenario}")
    if data is None:
        build(study, scenario, progress)
        data = _read_graphs(path)
    return data


def load(study: Study, scenario: str, progress: bool = False, key: Optional[str] = None) -> dict[str, list[Data]]:
    """{'train': [...], 'val': [...], 'test': [...]} complete graphs of a scenario (built when missing)."""
    return load_file(study, scenario, progress, key)["graphs"]


# ---- graph sizes per scenario and threshold (what a threshold changes) ----------------------------------------

def identical_thresholds(pair_len: torch.Tensor, thresholds) -> dict[float, float]:
    """``{threshold: the smallest threshold with identical graphs}`` for the thresholds whose graphs equal those of
    a smaller one: no node pair (of `pair_len`, every pair of every graph) has a length between the two. Edges only
    grow with the threshold, so equal edge totals mean equal graphs: the rule of `monolib.study.copies.same_graphs`."""
    out: dict[float, float] = {}
    source, source_edges = None, -1
    for t in sorted(set(float(t) for t in thresholds)):
        edges = int(pair_mask(pair_len, t).sum())
        if edges == source_edges:
            out[t] = source
        else:
            source, source_edges = t, edges
    return out
