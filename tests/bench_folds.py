"""How long one fold of `params/published_folds_quick.yaml` takes, on graph files of the release's size written
here (`tests/published_files.py`: 260 training files and 50 test files of 100 graphs), for docs/real-data.md.

    PYTHONPATH=. python tests/bench_folds.py <work folder>

Writes the files (once) and a copy of the study file pointing at them into the work folder, runs the graph stage
of fold 0 and a reduced grid of fold 0 in this process (gcn at 0, 1 m and infinity, ours at 0, layout at
infinity; seed 0), and writes ``<work folder>/fold_timing.json``: seconds of the graph stage and of each cell, the
epochs each cell ran and its training graphs, the machine and the date. Run again, it keeps those measurements
(its cells are complete: timing them again would time a read) and adds the extrapolation (`extrapolate`).
"""
from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import yaml

CELLS = [("gcn", 0.0), ("gcn", 1.0), ("gcn", float("inf")), ("ours", 0.0), ("layout", float("inf"))]


def extrapolate(timing: dict, full_graphs: int, folds: int, seeds: int, thresholds: int) -> dict:
    """The whole study from one fold's measurement, assuming the cells run one after the other (two jobs of two
    threads on two cores run about as fast as one job) and the same epochs at every size:

    - per split (the release and each fold): the graph stage, then for each seed one gcn cell per threshold (the
      mean of the measured gcn cells), one ``ours`` and one ``layout`` cell;
    - at full size the training part of each cell (``train_s``) scaled by the training + validation graphs of a
      fold at full size over those measured, the rest of the cell kept.
    """
    cells = timing["cells"]
    gcn = [c for c in cells if c["method"] == "gcn"]
    other = [c for c in cells if c["method"] != "gcn"]
    measured_graphs = timing["train_graphs"] + timing["val_graphs"]

    def split_seconds(scale: float) -> float:
        def cell(c):
            return c["seconds"] + c["train_s"] * (scale - 1)
        per_seed = thresholds * sum(map(cell, gcn)) / len(gcn) + sum(map(cell, other))
        return timing["graphs_s"] + seeds * per_seed

    scale = full_graphs / measured_graphs
    return {"splits": folds + 1, "seeds": seeds, "thresholds": thresholds, "full_train_val_graphs": full_graphs,
            "scale": round(scale, 2), "quick_size_hours": round((folds + 1) * split_seconds(1.0) / 3600, 2),
            "full_size_hours": round((folds + 1) * split_seconds(scale) / 3600, 2)}


def main(work: Path) -> dict:
    os.environ["MONOLIB_RUNS"] = str(work / "runs")  # before monolib reads it
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from monolib import paths
    from monolib.graphs import scenegraphs
    from monolib.params import load_study
    from monolib.retrieval.cell import run_cell
    from tests.published_files import release_size

    root = work / "graphs"
    if not (root / "test").is_dir():
        t = time.perf_counter()
        release_size(root)
        print(f"release-size files written in {time.perf_counter() - t:.0f} s", flush=True)
    spec = yaml.safe_load((paths.PARAMS / "published_folds.yaml").read_text())
    spec.update(yaml.safe_load((paths.PARAMS / "published_folds_quick.yaml").read_text()))
    spec["dataset"] = {**yaml.safe_load((paths.PARAMS / "published_folds.yaml").read_text())["dataset"],
                       **spec["dataset"]}
    spec.pop("extends")
    spec.update(name="bench_folds", graphs_root=str(root))
    (work / "bench_folds.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    study = load_study(work / "bench_folds.yaml")
    if (work / "fold_timing.json").is_file():
        out = json.loads((work / "fold_timing.json").read_text())
        full = load_study(work / "bench_folds.yaml")
        full.dataset.train_settings, full.dataset.train_frames_per_setting = None, 100  # published_folds.yaml's size
        from monolib.graphs import published
        picked = published.select(full.at_fold(0))
        out["extrapolation"] = extrapolate(out, len(picked["train"]) + len(picked["val"]), study.protocol.folds,
                                           len(study.seeds), len(study.thresholds))
        (work / "fold_timing.json").write_text(json.dumps(out, indent=1) + "\n")
        print(out["extrapolation"], flush=True)
        return out
    out: dict = {"machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
                 "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "threads": study.threads, "cells": []}
    t = time.perf_counter()
    scenegraphs.build_all(study.at_fold(0), ["s1"], progress=False)
    out["graphs_s"] = round(time.perf_counter() - t, 1)
    graphs = scenegraphs.load(study.at_fold(0), "s1")
    out["train_graphs"], out["val_graphs"] = len(graphs["train"]), len(graphs["val"])
    print(f"graph stage of fold 0: {out['graphs_s']} s ({out['train_graphs']} training graphs)", flush=True)
    for method, threshold in CELLS:
        t = time.perf_counter()
        record = run_cell(study, method, "s1", threshold, 0, fold=0)
        cell = {"method": method, "threshold": str(threshold), "seconds": round(time.perf_counter() - t, 1),
                "epochs_run": record.get("epochs_run"), "train_s": round(record["timings"].get("train_s", 0), 1)}
        out["cells"].append(cell)
        print(cell, flush=True)
    (work / "fold_timing.json").write_text(json.dumps(out, indent=1) + "\n")
    return main(work)  # + the extrapolation


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: PYTHONPATH=. python tests/bench_folds.py <work folder>")
    main(Path(sys.argv[1]).resolve())
