"""One cell of the ablation grid: (method, scenario, threshold, seed) -> train, embed, retrieve, write files.

`notebooks/ablation_cell.ipynb` calls `run_cell`; so do the tests. A cell writes into its folder:
`cell.json` (written last: its presence means the cell is complete; ``metrics`` per protocol), `rankings.csv` (top
10 per query and protocol), `protocol.csv` (which test frames were queries / positives in each protocol), both with
a leading ``protocol`` column (``paper``, ``siblings``: `monolib.retrieval.evaluate.evaluate_protocols`, one trained
encoder evaluated on both), `embeddings.npy` (every test frame) and, for trained methods,
`history.csv` and `model.pt` (the encoder's weights, used by `monolib index`). A cell whose graphs equal those of
a smaller threshold (`monolib.study.copies.same_graphs`) is a copy of that cell's files, and its `cell.json` says so
(`same_graphs_as`).
"""
from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd
import torch

from monolib import device as devices, methods, paths, versions
from monolib.data import dataset, selection
from monolib.data.protocols import family
from monolib.graphs import scenegraphs
from monolib.io import (
    atomic_path, load_cached, move_aside, read_json, read_json_dict, save_torch, write_json, write_text
)
from monolib.params import Study, StudyError, key_of
from monolib.perception import features
from monolib.retrieval import baselines, evaluate, gcn, metrics, pretrained

log = logging.getLogger(__name__)
IMAGE_SCENARIO = "rgb"  # image methods use neither the scenario's sources nor the threshold


def cell_folder(study: Study, method: str, scenario: str, threshold: float, seed: int,
                out_dir: Optional[str] = None) -> Path:
    return Path(out_dir) if out_dir else paths.cell_dir(study.name, method, scenario, threshold, seed, study.fold)


def inputs_key(study: Study, method: str, scenario: str, graph_key: Optional[str] = None,
               build: bool = False) -> str:
    """The key of what a cell reads: for a graph method its scenario's graphs (`graph_inputs`), for an image method
    the frames (the data stage's `dataset_key`), or their ImageNet features (`features.features_key`, which holds the
    dataset's). `graph_key`: the graph stage's `scenario_key`, when known."""
    if methods.kind(method, study) == "graph":
        return graph_inputs(study, scenario, graph_key, build)
    if method in methods.IMAGENET:
        return features.features_key(study)
    return dataset.dataset_key(study)


def graph_inputs(study: Study, scenario: str, graph_key: Optional[str] = None, build: bool = False) -> str:
    """The graph stage's `scenario_key` and, when the stage could not read some frames' files (empty graphs, the
    graphs file's ``missing``), which ones: a cell computed on graphs with other frames missing (or none) is not
    reused. With every frame read this is the scenario key itself, as it is while the graphs are not built yet
    (`build`: build them first; `run_cell` does, so a cell's record holds the key of the graphs it read)."""
    graph_key = graph_key or scenegraphs.scenario_key(study, scenario)
    if not build and not scenegraphs.graphs_path(study, scenario, graph_key).is_file():
        return graph_key
    missing = scenegraphs.load_file(study, scenario, key=graph_key).get("missing") or []
    return key_of({"graphs": graph_key, "unread": sorted(missing)}) if missing else graph_key


def cell_key(study: Study, method: str, scenario: str, threshold: float, seed: int,
             inputs: Optional[str] = None) -> str:
    """Cache key of a cell: its inputs' key (`inputs_key`, passed on by a caller that holds it), what it
    computes (a graph method's encoder settings, whatever its name; an image method's name), threshold, seed, the
    protocol's draw and the depth of its rankings (not the k of the metrics: any k up to that depth is recomputed
    from the rankings, `refresh_metrics`), the fold (folds by volume), the torch threads, device, deterministic mode,
    and the version of the cells' code and libraries."""
    graph_method = methods.kind(method, study) == "graph"
    inputs = inputs if inputs is not None else inputs_key(study, method, scenario)
    pr = study.protocol
    return key_of({**study.fold_key(), "inputs": inputs, "method": None if graph_method else method,
                   "encoder": dataclasses.asdict(study.gcn_spec(method)),  # (an image encoder trains on its schedule)
                   "threshold": paths.threshold_json(threshold) if graph_method else None, "seed": int(seed),
                   "protocol": {"settings": pr.settings, "siblings": pr.siblings, "families": pr.families,
                                "frames": pr.frames, "queries": pr.queries, "positives": pr.positives,
                                "ranked": evaluate.ranking_depth(pr)},
                   "val": study.gcn.val_settings, "threads": study.threads, "device": devices.device().type,
                   "deterministic": study.deterministic, "code": versions.code_version("cells"),
                   "libraries": versions.library_versions("cells")})


def refresh_metrics(folder: Path, study: Study, record: Optional[dict] = None) -> dict:
    """The record of a complete cell with exactly the metrics the study reports: recall@k and precision@k of k
    values the cell was not made with are computed from its rankings (the top `evaluate.ranking_depth`, part of
    its key; `metrics.metrics_from_rankings`, the definition `evaluate` used), and the record rewritten; a change
    of the reported k trains nothing. `record`: the cell's record, when the caller has read it."""
    record = record if record is not None else read_json(Path(folder) / "cell.json")
    pr = study.protocol
    want = set(metrics.metric_names(pr.recall_k, pr.precision_k))
    if all(set(m) == want for m in record["metrics"].values()):
        return record
    rankings = pd.read_csv(Path(folder) / "rankings.csv")
    record["metrics"] = {name: metrics.metrics_from_rankings(rankings[rankings["protocol"] == name], pr.recall_k,
                                                              pr.precision_k) for name in record["metrics"]}
    write_json(Path(folder) / "cell.json", record)
    log.info("cell %s: metrics at k %s recomputed from its rankings", folder, sorted(want))
    return record


def read_record(folder: Path) -> Optional[dict]:
    """A cell's `cell.json` through the one cache loader (`monolib.io.load_cached`): None when absent or unreadable
    (an unreadable one is removed with a warning, so the cell runs again)."""
    return load_cached(Path(folder) / "cell.json", lambda p: read_json_dict(p, ("metrics", "method")), "cell record")


def aside(folder: Path, key: str) -> Path:
    """Where the cell of `key` waits while a cell of another key holds its folder:
    ``cells/.aside/<method>/<name>@<key>/`` (out of the way of every reader of ``cells/<method>/<name>/``)."""
    folder = Path(folder)
    return folder.parent.parent / ".aside" / folder.parent.name / f"{folder.name}@{key}"


def take_over(folder: Path, key: str) -> Optional[dict]:
    """Make `folder` the cell of `key` without losing the cell of another key that holds it: another study file of
    the same name (other GCN settings), the same study on another device or with other code. That cell is moved
    aside (`aside`: nothing it wrote is deleted), and a cell of `key` kept aside earlier moves back.
    The cell's record when `folder` now holds the complete cell of `key`; otherwise None, and `folder` is absent,
    ready for it.
    Files of no complete cell (a killed run's) are removed. The study's lock (`monolib.locks`) keeps two runs of
    one study from taking one folder over at once."""
    folder = Path(folder)
    record = read_record(folder)
    if record is not None and record.get("key") == key:
        return record
    held = str(record["key"]) if record is not None and record.get("key") else None
    move_aside(folder, aside(folder, held) if held else None)  # (an older copy of that key's cell: replaced)
    if held:
        log.info("cell %s: a cell of key %s kept aside in %s", folder, held, aside(folder, held).name)
    mine = aside(folder, key)
    if mine.is_dir() and is_complete(mine, key):
        folder.parent.mkdir(parents=True, exist_ok=True)
        os.replace(mine, folder)
        log.info("cell %s: its cell of key %s moved back from %s", folder, key, mine.name)
        return read_record(folder)
    return None


def is_complete(folder: Path, key: Optional[str] = None) -> bool:
    """The cell's record is there and readable and, when `key` is given, was made by this key (the same inputs,
    settings and code): a cell of older code or other graphs is not complete."""
    record = read_record(folder)
    if record is None:
        return False
    if key is not None and record.get("key") != key:
        log.info("cell %s: made with key %s, expected %s: runs again", folder, record.get("key"), key)
        return False
    return True


def _check_cell(study: Study, method: str, scenario: str, threshold: float) -> str:
    """The kind of `method` (graph / image), or one `StudyError` for a cell the study cannot have."""
    if method not in methods.METHODS and method not in study.variants:
        known = sorted(methods.METHODS) + sorted(study.variants)
        raise StudyError(f"method {method!r}: unknown (known: {', '.join(known)})")
    kind = methods.kind(method, study)
    if kind == "graph" and scenario not in study.scenarios:
        raise StudyError(f"scenario {scenario!r}: not in {study.path} (scenarios: {', '.join(study.scenarios)})")
    if not threshold >= 0:
        raise StudyError(f"threshold {threshold}: expected 0 (no edges), a distance in metres > 0, or inf")
    return kind


def _graph_embeddings(study: Study, method: str, scenario: str, threshold: float, seed: int, graph_key: str,
                      timings: dict) -> tuple:
    """Train a graph encoder on the scenario's graphs at `threshold` and embed the test graphs:
    ``(embeddings, test frames, their settings, extra record fields, history, state dict)``."""
    t = time.perf_counter()
    spec = study.gcn_spec(method)
    graphs = scenegraphs.load(study, scenario, key=graph_key)
    projection = study.projection(scenario)
    split = {k: [gcn.encoder_graph(g, threshold, spec, projection) for g in v] for k, v in graphs.items()}
    timings["graphs_s"] = time.perf_counter() - t
    t = time.perf_counter()
    result = gcn.train(split["train"], split["val"], spec, seed=seed, threads=study.threads,
                       deterministic=study.deterministic)
    timings["train_s"] = time.perf_counter() - t
    t = time.perf_counter()
    emb = gcn.embed(result.model, split["test"]).numpy()
    state = {k: v.detach().cpu() for k, v in result.model.state_dict().items()}  # loadable on any machine
    test = split["test"]
    extra = {"best_epoch": result.best_epoch, "epochs_run": len(result.history),
             "test_nodes_mean": float(np.mean([g.num_nodes for g in test])),
             "test_edges_mean": float(np.mean([g.edge_index.shape[1] for g in test])),
             "test_empty_graphs": int(sum(g.num_nodes == 0 for g in test))}
    if study.fold is not None:  # a fold's volumes on each side, as the cell read them (none on both)
        extra["volumes"] = {"train": sorted({family(g.setting) for g in graphs["train"] + graphs["val"]}),
                            "test": sorted({family(g.setting) for g in test})}
    timings["embed_s"] = time.perf_counter() - t
    return emb, [g.frame for g in test], [g.setting for g in test], extra, pd.DataFrame(result.history), state


def _image_embeddings(study: Study, method: str, seed: int, timings: dict) -> tuple:
    """An image method's embeddings of the test frames, as `_graph_embeddings` returns them."""
    ds = dataset.open_dataset(study)
    sel = selection.select_frames(study, ds, study.gcn.val_settings)
    timings["graphs_s"] = 0.0
    t = time.perf_counter()
    embed = pretrained.embed if method in methods.IMAGENET else baselines.embed
    emb, extra, history, state = embed(method, study, sel, seed)
    timings["embed_s"] = time.perf_counter() - t
    return emb, [f.key for f in sel.test], [f.setting for f in sel.test], extra, history, state


def scenario_fields(study: Study, scenario: str, graph: bool = True) -> dict:
    """What a cell's record says of its scenario: the scenario, its label, sources, depth scale, and (for a graph
    method) the projection and node colour space its graphs were built in."""
    sc = study.scenarios.get(scenario)
    graph = bool(sc) and graph
    return {"scenario": scenario, "scenario_label": sc.label if sc else "RGB only (no graph)",
            "depth": sc.depth if sc else None, "semantic": sc.semantic if sc else None,
            "depth_scale": sc.depth_scale if sc else None,
            "projection": study.projection(scenario) if graph else None,
            "colour": study.colour(scenario) if graph else None}


def _record(study: Study, method: str, kind: str, key: str, scenario: str, threshold: float, seed: int,
            evaluated: dict, timings: dict, extra: dict) -> dict:
    """The `cell.json` content of a computed cell."""
    pr = study.protocol
    return {
        "method": method, "kind": kind, "key": key,
        "encoder": dataclasses.asdict(study.gcn_spec(method)) if kind == "graph" else None,
        "threshold": paths.threshold_json(threshold), "seed": int(seed), "study": study.name,
        "study_file": study.path, **({"fold": study.fold} if study.fold is not None else {}),
        **scenario_fields(study, scenario, kind == "graph"),
        "protocol": {"settings": pr.settings, "siblings": pr.siblings, "frames": pr.frames, "queries": pr.queries,
                     "positives": pr.positives},
        "protocols": {name: {"settings": r.settings, "draw_seed": r.seed} for name, r in evaluated.items()},
        "metrics": {name: r.metrics for name, r in evaluated.items()}, "timings": timings, **extra,
    }


def _write_cell(folder: Path, record: dict, evaluated: dict, emb, history, state) -> None:
    """A computed cell's files, `cell.json` last (its presence marks the cell complete)."""
    write_text(folder / "rankings.csv", pd.concat([r.rankings for r in evaluated.values()]).to_csv(index=False))
    write_text(folder / "protocol.csv",
               pd.concat([r.protocol_table() for r in evaluated.values()]).to_csv(index=False))
    with atomic_path(folder / "embeddings.npy") as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(emb, dtype=np.float32))
    if history is not None:
        write_text(folder / "history.csv", history.to_csv(index=False))
    if state is not None:
        save_torch(folder / "model.pt", state)
    write_json(folder / "cell.json", record)  # last: marks the cell complete


def run_cell(study: Study, method: str, scenario: str, threshold: float, seed: int, out_dir: Optional[str] = None,
             force: bool = False, fold: Optional[int] = None) -> dict:
    """Run one cell and return its `cell.json` content (read back when the cell is already complete). `fold`: the
    fold of a study with `protocol.split: volumes` (its graphs, its folder ``...__f<fold>``)."""
    threshold = float(threshold)
    study = study.at_fold(fold)
    kind = _check_cell(study, method, scenario, threshold)
    folder = cell_folder(study, method, scenario, threshold, seed, out_dir)
    graph_key = scenegraphs.scenario_key(study, scenario) if kind == "graph" else None
    inputs = inputs_key(study, method, scenario, graph_key, build=True)  # the graphs' (the frames' for an image one)
    key = cell_key(study, method, scenario, threshold, seed, inputs)
    if force:
        record = None
    elif out_dir is None:
        record = take_over(folder, key)  # a cell of another key in the folder: kept aside, not lost
    else:
        record = read_record(folder) if is_complete(folder, key) else None
    if record is not None:
        log.info("cell %s already complete", folder)
        return refresh_metrics(folder, study, record)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cell.json").unlink(missing_ok=True)  # (an `out_dir` of the caller's, or `force`): written anew
    torch.set_num_threads(study.threads)
    devices.keep_freed_memory()
    timings: dict[str, float] = {}  # graphs_s, train_s (trained graph encoders), embed_s, retrieval_s
    if kind == "graph":
        emb, frames, settings, extra, history, state = _graph_embeddings(study, method, scenario, threshold, seed,
                                                                         graph_key, timings)
    else:
        emb, frames, settings, extra, history, state = _image_embeddings(study, method, seed, timings)
    t = time.perf_counter()
    evaluated = evaluate.evaluate_protocols(emb, frames, settings, study.protocol, seed)
    timings["retrieval_s"] = time.perf_counter() - t
    record = _record(study, method, kind, key, scenario, threshold, seed, evaluated, timings, extra)
    _write_cell(folder, record, evaluated, emb, history, state)
    return record


def copy_cell(source: Path, folder: Path, threshold: float, source_name: str, key: Optional[str] = None,
              scenario: Optional[dict] = None) -> dict:
    """The results of the cell in `source` as those of `threshold` (the two read identical inputs): its files
    copied, `cell.json` with this threshold and ``same_graphs_as`` naming the source (written last, as always).
    `scenario`: the `scenario_fields` of a cell of another scenario whose encoder reads the same inputs as the
    source's (``same_inputs_as`` then names the source: its own scenario's row of a report counts it)."""
    t = time.perf_counter()
    record = read_json(source / "cell.json")
    folder.mkdir(parents=True, exist_ok=True)
    for f in source.iterdir():
        if f.is_file() and f.name != "cell.json" and not f.name.startswith("."):  # not a killed write's temp file
            with atomic_path(folder / f.name) as tmp:
                shutil.copyfile(f, tmp)
    record.update(threshold=paths.threshold_json(threshold), timings={"copy_s": time.perf_counter() - t})
    if scenario is None:
        record["same_graphs_as"] = source_name
    else:
        record.update(scenario, same_inputs_as=source_name)
    if key is not None:
        record["key"] = key  # this cell's own key (its threshold), so that `is_complete(folder, key)` holds
    write_json(folder / "cell.json", record)
    return record
