"""What the grid costs and how it scales: `monolib bench grid` (`make bench-grid`, writes `figures/scaling.json`).

`measure` runs the cells of a small study (the smoke study by default) from empty cell folders, over the same cached
dataset, perception and graphs, on three engines: the local path (the study's `jobs` worker processes), a local Dask
cluster of 1 worker and one of 2 workers (`distributed.LocalCluster`, one single-threaded worker process each, as
`dask worker --nthreads 1` starts them); each engine twice, side by side in one run: with a kernel per cell
(``MONOLIB_KERNELS=cold``) and with one warm kernel per worker (`monolib.study.kernels`, the default). Each run gives
cells per minute; every cell's wall time (the papermill notebook, kernel start included) is set against the compute time
its `cell.json` records (`timings`: graphs, train, embed, retrieval), which gives the notebook overhead per cell.

`project` turns those costs into the hours of the paper study (`params/paper.yaml`: ~12,000 frames, 5 thresholds x
5 seeds x 4 scenarios, with and without the encoder variants of `params/ablations.yaml`) on 1, 8 and 64 workers.
Its model, stated so that it can be checked: a GCN cell costs the notebook overhead measured above (wall time minus
the compute its `cell.json` records), plus its training: the paper's training graphs times its epochs (`gcn.epochs`,
an upper bound: early stopping ends most runs sooner) times the seconds per (graph x epoch) of `gcn.train` timed
here with the paper's encoder settings (batch size, layers) on the measured study's graphs repeated to a
paper-sized epoch (the smoke cells' own training is too small to measure it: a few batches per epoch, where fixed
costs dominate). Cells are independent and of equal cost, so W workers take ceil(cells / W) rounds. The measured
graphs and real Hypersim's have about the same number of nodes (both recorded), which is what lets a per-graph cost
carry over.
"""
from __future__ import annotations

import dataclasses
import math
import os
import shutil
import time
from pathlib import Path

import numpy as np

from monolib import methods, paths
from monolib.graphs import build as graph, scenegraphs
from monolib.graphs.fidelity import read_reference
from monolib.io import read_json, write_json, write_text
from monolib.params import load_study
from monolib.retrieval import gcn
from monolib.study import runner

WORKERS = (1, 8, 64)
KERNELS = ("cold", "warm")  # monolib.study.kernels: a kernel per cell, or one warm kernel per worker
PAPER_TRAIN_FRAMES = 11_300  # the paper, "Hypersim Dataset": ~12,000 images, 11,300 of them for training


def _study_file(base: str, engine: str) -> Path:
    """A study that `extends` the base (its dataset, models and graphs) with cells of its own."""
    name = f"{base}_scaling_{engine}"
    path = paths.study_dir(name) / f"{name}.yaml"
    write_text(path, f"extends: {base}\nname: {name}\n")
    return path


def _one_run(base: str, engine: str, jobs: int, scheduler: str | None) -> dict:
    path = _study_file(base, engine)
    s = load_study(str(path))
    for sub in ("cells", "notebooks"):
        shutil.rmtree(s.dir / sub, ignore_errors=True)
    t0 = time.perf_counter()
    grid = runner.run_grid(s, jobs=jobs, progress=False, scheduler=scheduler)
    seconds = time.perf_counter() - t0

    records = {c.name: read_json(paths.cell_dir(s.name, c.method, c.scenario, c.threshold, c.seed) / "cell.json")
               for c in runner.grid(s) if c.name in grid["cell_seconds"]}
    per_cell = [{"cell": name, "wall_s": round(wall, 2), "compute_s": round(sum(records[name]["timings"].values()), 2),
                 "train_s": round(records[name]["timings"].get("train_s", 0.0), 2),
                 "epochs_run": records[name].get("epochs_run")} for name, wall in sorted(grid["cell_seconds"].items())]
    return {"seconds": round(seconds, 1), "cells": grid["cells"], "computed": len(per_cell),
            "cells_per_minute": round(60 * len(per_cell) / seconds, 2), "per_cell": per_cell}


def measure(base: str = "smoke", dask_workers: tuple[int, ...] = (1, 2)) -> dict:
    """Cells per minute of the base study's grid on the local path and on local Dask clusters (see the module)."""
    from distributed import LocalCluster

    s = runner.prepare(base, progress=False)  # dataset, perception, graphs: cached, not timed
    out = {"study": base, "jobs": s.jobs, "threads_per_cell": s.threads, "engines": {}}
    saved = os.environ.get("MONOLIB_KERNELS")
    try:
        for kernels in KERNELS:  # side by side in one run: a kernel per cell, then one warm kernel per worker
            os.environ["MONOLIB_KERNELS"] = kernels
            out["engines"][f"local_{kernels}"] = {"workers": s.jobs, "kernels": kernels,
                                                  **_one_run(base, f"local_{kernels}", s.jobs, None)}
            for n in dask_workers:
                t0 = time.perf_counter()
                with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
                    start = time.perf_counter() - t0
                    out["engines"][f"dask{n}_{kernels}"] = {
                        "workers": n, "kernels": kernels, "cluster_start_s": round(start, 1),
                        **_one_run(base, f"dask{n}_{kernels}", n, cluster.scheduler_address)}
    finally:
        if saved is None:
            os.environ.pop("MONOLIB_KERNELS", None)
        else:
            os.environ["MONOLIB_KERNELS"] = saved
    out["training"] = training_rate(s, load_study("paper", check_files=False))
    return out


def training_rate(study, paper, graphs: int = 2048, epochs: int = 2, threshold: float = 2.0) -> dict:
    """Seconds per (training graph x epoch) of `gcn.train` with `paper`'s encoder settings, on `study`'s
    ground-truth training graphs (at `threshold`) repeated to `graphs` graphs, at `study`'s torch threads."""
    source = scenegraphs.load(study, next(iter(study.scenarios)))
    train = [graph.at_threshold(g, threshold) for g in source["train"]]
    repeated = [train[i % len(train)] for i in range(graphs)]
    spec = dataclasses.replace(paper.gcn, epochs=epochs, patience=epochs + 1)
    t0 = time.perf_counter()
    gcn.train(repeated, [graph.at_threshold(g, threshold) for g in source["val"]], spec, seed=study.seed,
              threads=study.threads, deterministic=study.deterministic)
    seconds = time.perf_counter() - t0
    return {"graphs": graphs, "epochs": epochs, "batch_size": spec.batch_size, "threads": study.threads,
            "seconds": round(seconds, 2), "s_per_graph_epoch": seconds / (graphs * epochs),
            "nodes_per_graph": round(float(np.mean([g.num_nodes for g in train])), 2)}


def project(measured: dict, paper: str = "paper", variants_from: str = "ablations") -> dict:
    """Hours of the paper study's GCN cells on 1, 8 and 64 workers from `measured`'s per-cell costs."""

    def overhead_of(kernels: str) -> float:
        cells = [c for e in measured["engines"].values() if e.get("kernels", "cold") == kernels for c in e["per_cell"]]
        return float(np.median([c["wall_s"] - c["compute_s"] for c in cells])) if cells else float("nan")

    overheads = {k: round(overhead_of(k), 1) for k in KERNELS}
    overhead = overheads["warm"] if math.isfinite(overheads["warm"]) else overheads["cold"]  # the runner's default
    rate = measured["training"]["s_per_graph_epoch"]
    study = load_study(paper, check_files=False)
    train_graphs = PAPER_TRAIN_FRAMES
    cell_s = rate * train_graphs * study.gcn.epochs + overhead
    extra = {}  # the other study's variants, on the paper study's scenarios (one of its own, e.g. s1_exact: left out)
    for name, v in load_study(variants_from, check_files=False).variants.items():
        kept = [sc for sc in v.scenarios if sc in study.scenarios] if v.scenarios else None
        if kept is None or kept:
            extra[name] = dataclasses.replace(v, scenarios=kept)
    with_variants = dataclasses.replace(study, variants={**study.variants, **extra})
    counts = {}
    for label, s in (("paper", study), ("paper + encoder variants", with_variants)):
        counts[label] = sum(methods.kind(c.method, s) == "graph" for c in runner.grid(s))
    hours = {label: {str(w): round(math.ceil(n / w) * cell_s / 3600, 2) for w in WORKERS}
             for label, n in counts.items()}
    return {"train_s_per_graph_epoch": round(rate, 6), "overhead_s_per_cell": round(overhead, 1),
            "overhead_s_per_cell_by_kernels": overheads,
            "paper_train_graphs": train_graphs,
            "paper_epochs": study.gcn.epochs, "paper_cell_minutes": round(cell_s / 60, 1),
            "graph_cells": counts, "hours": hours, "workers": list(WORKERS),
            "nodes_per_graph": {"measured": measured["training"]["nodes_per_graph"],
                                "real_hypersim_train":
                                    read_reference()["real Hypersim, train"]["nodes per graph, mean"]}}


def markdown(record: dict) -> str:
    """The measured cells per minute and the projection, as docs/cluster.md shows them (`figures/scaling.md`)."""
    p = record["projection"]
    lines = [f"**The {record['study']} grid on each engine** ({record['machine']}, {record['cpus']} cores, "
             f"{record['date']}; {record['threads_per_cell']} torch threads per cell; `monolib bench grid`)", "",
             "| engine | kernels | workers | cells computed (copied) | seconds | cells per minute | "
             "notebook overhead per cell (s, median) |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for name, e in record["engines"].items():
        label = ("local process pool (no `--scheduler`)" if name.startswith("local") else
                 f"local Dask cluster (`--scheduler`), started in {e.get('cluster_start_s', 0):.0f} s")
        kernels = {"cold": "a kernel per cell", "warm": "one warm kernel per worker"}[e.get("kernels", "cold")]
        over = (float(np.median([c["wall_s"] - c["compute_s"] for c in e["per_cell"]])) if e["per_cell"]
                else float("nan"))
        lines.append(f"| {label} | {kernels} | {e['workers']} | {e['computed']} ({e['cells'] - e['computed']}) | "
                     f"{e['seconds']:.0f} | {e['cells_per_minute']:.2f} | {over:.1f} |")
    t = record["training"]
    lines += ["", f"**The paper study projected** from these runs and one timed training: "
              f"{p['overhead_s_per_cell']:.1f} s of notebook overhead per cell in warm kernels (median over the "
              f"warm cell runs of their wall time minus the compute their `cell.json` records; "
              f"{p.get('overhead_s_per_cell_by_kernels', {}).get('cold', float('nan')):.1f} s with a kernel per cell), "
              f"and {1000 * p['train_s_per_graph_epoch']:.2f} ms of GCN training per graph "
              f"and epoch (`gcn.train` with the paper's encoder settings, batch {t['batch_size']}, {t['threads']} "
              f"threads: {t['graphs']} graphs x {t['epochs']} epochs in {t['seconds']:.0f} s; the graphs have "
              f"{p['nodes_per_graph']['measured']:.1f} nodes on average, real Hypersim's "
              f"{p['nodes_per_graph']['real_hypersim_train']:.1f}). A paper cell ({p['paper_train_graphs']:,} training "
              f"graphs x {p['paper_epochs']} epochs, an upper bound: early stopping ends most runs sooner) then takes "
              f"{p['paper_cell_minutes']:.0f} min on one worker.", "",
             "| study | GCN cells | " + " | ".join(f"{w} worker{'s' * (w > 1)} (h)" for w in p["workers"]) + " |",
             "|---|---:|" + "---:|" * len(p["workers"])]
    for label, hours in p["hours"].items():
        lines.append(f"| {label} | {p['graph_cells'][label]} | "
                     + " | ".join(f"{h:.1f}" for h in hours.values()) + " |")
    return "\n".join(lines) + "\n"


def run(base: str = "smoke", out: str | None = None) -> dict:
    """`measure` and `project`, printed; with `out`, written as JSON (docs/cluster.md shows `figures/scaling.md`)."""
    import os
    import platform

    record = {"machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
              "date": time.strftime("%Y-%m-%d"), **measure(base)}
    record["projection"] = project(record)
    text = markdown(record)
    print(text, end="")
    if out:
        write_json(out, record)
        write_text(Path(out).with_suffix(".md"), text)
        print(f"written: {out} and {Path(out).with_suffix('.md').name}")
    return record
