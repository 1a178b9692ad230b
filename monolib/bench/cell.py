"""`monolib bench cell` (`make bench-cell`, figures/cell_profile.json and .md): where a grid cell's seconds go.

Three views of the same question, on a finished study (its graphs built, its cells run):

- the grid: each method's cells' own seconds (graphs, training, embedding, retrieval; from their ``cell.json``)
  summed, against the cells stage's wall time on its workers (``timings.json``); what is left is the runner's
  overhead (notebooks, kernels, files, waiting);
- one `gcn` cell's training (the study's first scenario, 1 m, seed 0, the study's own schedule on one thread),
  timed alone and under `torch.profiler`: the operators by their share of the CPU time;
- the floor: the dense products of that training (5 layers forward, their weight and input gradients backward,
  at the mean number of nodes of a batch) at the matrix product's measured rate on this machine, as a share of the
  training's seconds: what no change short of other arithmetic can remove.
"""
from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from monolib import device as devices, paths
from monolib.bench.common import written
from monolib.graphs import scenegraphs
from monolib.io import read_json
from monolib.params import load_study
from monolib.report.results import cell_files
from monolib.retrieval import gcn, grid

PARTS = ("graphs_s", "train_s", "embed_s", "retrieval_s")


def grid_seconds(study) -> dict:
    """Each method's cells' own seconds (`PARTS`) summed, and the cells stage's wall time times its jobs."""
    per_method = {}
    for f in cell_files(study.name, grid.names(study)):
        rec = read_json(f)
        row = per_method.setdefault(rec["method"], {**{p: 0.0 for p in PARTS}, "cells": 0, "copies": 0})
        timings = rec.get("timings") or {}
        row["copies" if "copy_s" in timings else "cells"] += 1
        for p in PARTS:
            row[p] += float(timings.get(p, 0.0))
    timings_file = paths.figures_dir(study.name) / "timings.json"
    stage = read_json(timings_file)["stage_seconds"].get("cells") if timings_file.is_file() else None
    own = sum(sum(r[p] for p in PARTS) for r in per_method.values())
    return {"per_method": {m: {k: round(v, 1) if isinstance(v, float) else v for k, v in r.items()}
                           for m, r in sorted(per_method.items())},
            "cells_own_s": round(own, 1), "stage_wall_s": stage, "jobs": study.jobs,
            "overhead_s": None if stage is None else round(stage * study.jobs - own, 1)}


def matmul_gflops(rows: int, width: int, repeat: int = 200) -> float:
    """The rate of a (rows x width) @ (width x width) float32 product on this thread, in GFLOP/s."""
    a, w = torch.randn(rows, width), torch.randn(width, width)
    for _ in range(10):
        a @ w
    t = time.perf_counter()
    for _ in range(repeat):
        a @ w
    return 2.0 * rows * width * width * repeat / (time.perf_counter() - t) / 1e9


def training_profile(study, scenario: str, threshold: float = 1.0, seed: int = 0, top: int = 12) -> dict:
    """One `gcn` cell's training, timed alone, then profiled; the operators' shares and the dense floor."""
    spec = study.gcn_spec("gcn")
    graphs = scenegraphs.load(study, scenario)
    split = {k: [gcn.encoder_graph(g, threshold, spec, study.projection(scenario)) for g in v]
             for k, v in graphs.items()}
    torch.set_num_threads(1)
    devices.keep_freed_memory()
    t = time.perf_counter()
    gcn.train(split["train"], split["val"], spec, seed=seed, threads=1)
    seconds = time.perf_counter() - t
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        gcn.train(split["train"], split["val"], dataclasses.replace(spec, epochs=min(spec.epochs, 3)), seed=seed,
                  threads=1)
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    ops = sorted(events, key=lambda e: -e.self_cpu_time_total)[:top]
    nodes = np.array([g.num_nodes for g in split["train"]])
    steps = spec.epochs * -(-len(nodes) // spec.batch_size)  # the triplet loop: batches of anchors per epoch
    batch_nodes = 3 * spec.batch_size * float(nodes.mean())  # anchors, positives, negatives
    rate = matmul_gflops(int(batch_nodes), spec.hidden)
    dims = [spec.hidden] * (spec.layers - 1) + [spec.out]  # each layer's output width (the first reads few columns)
    flops = sum(2.0 * batch_nodes * spec.hidden * d for d in dims[1:])  # layers 2-5: hidden -> d
    floor_s = 3 * flops * steps / (rate * 1e9)  # forward, and the weight and input gradients backward
    return {"scenario": scenario, "threshold": threshold, "seed": seed, "epochs": spec.epochs,
            "train_graphs": len(nodes), "nodes_per_graph": round(float(nodes.mean()), 2), "steps": steps,
            "train_s": round(seconds, 2), "ms_per_step": round(1000 * seconds / steps, 2),
            "matmul_gflops": round(rate, 1), "dense_floor_s": round(floor_s, 2),
            "dense_floor_share": round(floor_s / seconds, 3),
            "operators": [{"name": e.key, "calls": e.count, "self_share": round(e.self_cpu_time_total / total, 3)}
                          for e in ops]}


def cell_page(record: dict) -> str:
    """figures/cell_profile.md: the grid's seconds by method, then the training profile."""
    g, p = record["grid"], record["training"]
    rows = pd.DataFrame([{"method": m, **r} for m, r in g["per_method"].items()])
    lines = [f"# Where a grid cell's seconds go ({record['study']})", "",
             f"`monolib bench cell --study {record['study']}` on {record['cpu']}, {record['cores']} cores, "
             f"{record['date']}.", "",
             "## The grid: the cells' own seconds against the stage's wall time", "",
             rows.to_markdown(index=False), "",
             f"The cells' own seconds: {g['cells_own_s']}; the cells stage: {g['stage_wall_s']} s of wall time on "
             f"{g['jobs']} workers ({record['study']}'s timings.json), so the runner's overhead (notebooks, kernels, "
             f"files, waiting) is {g['overhead_s']} worker-seconds.", "",
             f"## One `gcn` cell's training ({p['scenario']}, {p['threshold']} m, seed {p['seed']}, one thread)", "",
             f"{p['epochs']} epochs over {p['train_graphs']} graphs of {p['nodes_per_graph']} nodes on average: "
             f"{p['steps']} steps in {p['train_s']} s ({p['ms_per_step']} ms a step). The matrix product runs at "
             f"{p['matmul_gflops']} GFLOP/s here; at that rate the training's dense products alone take "
             f"{p['dense_floor_s']} s, {100 * p['dense_floor_share']:.0f} % of its time: the floor of any change "
             f"that keeps the arithmetic.", "",
             "Operators by their share of the profiled CPU time (3 epochs under `torch.profiler`):", "",
             pd.DataFrame(p["operators"]).to_markdown(index=False), ""]
    return "\n".join(lines)


def run(study_name: str = "quick", out: str | Path | None = None) -> dict:
    """The record of `monolib bench cell`, written to `out` (JSON, and its page beside it) when given."""
    study = load_study(study_name)
    scenario = next(iter(study.scenarios))
    record = {"study": study.name, "cpu": devices.cpu_signature(), "cores": os.cpu_count(),
              "date": time.strftime("%Y-%m-%d"), "grid": grid_seconds(study),
              "training": training_profile(study, scenario)}
    print(cell_page(record))
    return written(record, str(out) if out else None, cell_page)
