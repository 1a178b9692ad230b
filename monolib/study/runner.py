"""The study runner: dataset -> perception -> graphs -> the papermill grid of cells -> the report notebook.

Every stage is cached by the parameters it depends on and skipped when its files exist, so a killed run is
resumed by running the same command again, and changing a GCN setting redoes only the cells. Which cells copy
another's results: `monolib.study.copies`; how a notebook runs: `monolib.study.notebooks`.
"""
from __future__ import annotations

import logging
import os
import time
from concurrent.futures import as_completed
from pathlib import Path

from monolib import lockfile, locks, methods, paths
from monolib.device import keep_freed_memory
from monolib.data import dataset, digest
from monolib.graphs import fidelity, scenegraphs
from monolib.io import write_json
from monolib.params import Study, StudyError, load_study
from monolib.perception import features, predictions
from monolib.perception.images import FrameRgb
from monolib.progress import tqdm
from monolib.report import graph_sizes, perception_figures, readme, viz
from monolib.retrieval.cell import (IMAGE_SCENARIO, cell_key, copy_cell, graph_inputs, is_complete,
                                    refresh_metrics, run_cell, scenario_fields, take_over)
from monolib.retrieval.grid import CellSpec, grid  # (the grid: monolib.retrieval.grid; re-exported)
from monolib.study import cluster
from monolib.study.copies import same_graphs
from monolib.study.notebooks import (CELL_NOTEBOOK, REPORT_NOTEBOOK, NotebookFailed, check_notebook_parameters, execute,
                                     run_cell_notebook)

log = logging.getLogger(__name__)


# The image methods that train an encoder (tens of seconds a cell on one thread, against a few seconds for a graph
# cell): started first, so that no long cell is left running alone at the end of the grid while the other workers
# idle (longest-processing-time-first). The order of the cells changes no number: each cell is seeded on its own.
LONG_CELLS = ("imagenet_triplet", "image_triplet", "orb_bow")


def longest_first(cells: list[CellSpec]) -> list[CellSpec]:
    """`cells` in the order the workers start them: `LONG_CELLS`' methods first (in that order), then the rest in
    grid order."""
    return sorted(cells, key=lambda c: LONG_CELLS.index(c.method) if c.method in LONG_CELLS else len(LONG_CELLS))


def _cell_notebook_path(study_name: str, cell_name: str) -> Path:
    """Where the runner writes the executed notebook of a cell (`runs/<study>/notebooks/cells/`)."""
    return paths.study_dir(study_name) / "notebooks" / "cells" / f"{cell_name.replace('/', '__')}.ipynb"


def _cell_keys(study: Study, cells: list[CellSpec]) -> tuple[dict[str, str], dict]:
    """``({cell name: its key}, {fold: the graph stage's keys})`` of the grid's cells; the graphs of each fold are
    built first (a cell's key holds the frames its graphs could not read)."""
    data_key = dataset.dataset_key(study)  # the upstream stages' keys, once: each cell's key is its inputs' + its own
    graph_cells = {(c.fold, c.scenario) for c in cells if methods.kind(c.method, study) == "graph"}
    folds = sorted({f for f, _ in graph_cells}, key=lambda f: -1 if f is None else f)
    scenario_keys = {f: scenegraphs.scenario_keys(study.at_fold(f), data_key) for f in folds}
    inputs = {(f, sc): graph_inputs(study.at_fold(f), sc, scenario_keys[f][sc], build=True)  # + unread frames
              for f, sc in sorted(graph_cells, key=lambda fs: (-1 if fs[0] is None else fs[0], fs[1]))}
    image_inputs = {m: features.features_key(study, data_key) if m in methods.IMAGENET else data_key
                    for m in {c.method for c in cells}}
    keys = {c.name: cell_key(study.at_fold(c.fold), c.method, c.scenario, c.threshold, c.seed,
                             inputs[c.fold, c.scenario] if methods.kind(c.method, study) == "graph"
                             else image_inputs[c.method])
            for c in cells}
    return keys, scenario_keys


def _run_in_process(study: Study, run: list[CellSpec], progress: bool, failed: list, seconds: dict) -> None:
    """`run_cell` for each cell of `run`, one after the other in this process."""
    for c in tqdm(run, desc="cells", unit="cell", disable=not progress):
        try:
            t = time.perf_counter()
            run_cell(study, c.method, c.scenario, c.threshold, c.seed, fold=c.fold)
            seconds[c.name] = time.perf_counter() - t
        except Exception as exc:
            failed.append((c.name, exc))
            log.error("cell %s failed: %s: %s", c.name, type(exc).__name__, exc)


def _run_notebooks(study: Study, run: list[CellSpec], jobs: int, progress: bool, scheduler: str | None,
                   failed: list, seconds: dict) -> None:
    """Each cell of `run` as a notebook, on `jobs` local workers or the Dask scheduler at `scheduler`."""
    env = cluster.task_environment()
    if scheduler:  # each task checks, on its worker and before it computes, what decides its numbers
        import json

        env[cluster.FINGERPRINT_ENV] = json.dumps(cluster.fingerprint(str(study.path)), sort_keys=True)
    with cluster.Workers(study, jobs, scheduler) as workers:
        print(f"cells on {workers.describe()}", flush=True)
        futures = {workers.submit(c.name, run_cell_notebook, study.path, c,
                                  str(_cell_notebook_path(study.name, c.name)), study.cell_timeout, env): c
                   for c in run}
        bar = tqdm(total=len(run), desc="cells", unit="cell", disable=not progress)
        for fut in as_completed(futures):
            try:
                seconds[futures[fut].name] = fut.result()
            except Exception as exc:
                failed.append((futures[fut].name, exc))
                log.error("cell %s failed: %s: %s", futures[fut].name, type(exc).__name__, exc)
            bar.update(1)
        bar.close()


def _grid_failures(study: Study, failed: list, run: list[CellSpec], n_cells: int, in_process: bool) -> None:
    """One `NotebookFailed` listing the failed cells (nothing when none failed)."""
    if not failed:
        return
    ran, lines = {c.name for c in run}, []
    for name, exc in failed:
        if name not in ran:  # a copy whose source cell failed
            lines.append(f"{name}: {exc}")
        elif in_process:
            lines.append(name)
        else:
            lines.append(f"{name} (executed notebook: {_cell_notebook_path(study.name, name)})")
    raise NotebookFailed(f"{len(failed)} of {n_cells} cells failed (their errors are above):"
                         + "".join(f"\n  {ln}" for ln in lines) + "\nre-run to retry only these")


def run_grid(study: Study, jobs: int | None = None, progress: bool = True, in_process: bool = False,
             scheduler: str | None = None) -> dict:
    """Run every cell that has no results yet through papermill: in `jobs` local worker processes, or as tasks of
    the Dask scheduler at `scheduler` (`monolib.study.cluster`; its workers share the runs folder). `in_process`:
    `monolib.retrieval.cell.run_cell` one cell after the other in this process, no kernel per cell: what `prepare` does
    for a notebook; the same function computes the same files. With folds by volume every fold's cells are in the grid
    (`monolib.retrieval.grid.grid`), each in its own folder."""

    def folder(c: CellSpec) -> Path:
        return paths.cell_dir(study.name, c.method, c.scenario, c.threshold, c.seed, c.fold)

    cells = grid(study)
    keys, scenario_keys = _cell_keys(study, cells)
    records = {c.name: take_over(folder(c), keys[c.name]) for c in cells}  # another key's cell: kept aside, not lost
    todo = [c for c in cells if records[c.name] is None]
    for c in cells:
        if records[c.name] is not None:  # the reported k may have changed: from the rankings, no training
            refresh_metrics(folder(c), study, records[c.name])
    copies = same_graphs(study, cells, scenario_keys.get(None)) if todo else {}
    run = longest_first([c for c in todo if c.name not in copies])
    log.debug("grid: %d cells, %d done, %d to run, %d to copy", len(cells), len(cells) - len(todo), len(run),
              len(todo) - len(run))
    print(f"grid: {len(cells)} cells, {len(cells) - len(todo)} already complete, {len(todo)} to run "
          f"({len(todo) - len(run)} of them read the inputs of another cell: copied from it)", flush=True)
    failed: list = []
    seconds: dict[str, float] = {}  # wall seconds of each cell run (a notebook: kernel start included)
    t0 = time.perf_counter()
    if run and in_process:
        _run_in_process(study, run, progress, failed, seconds)
    elif run:
        _run_notebooks(study, run, jobs or study.jobs, progress, scheduler, failed, seconds)
    for c in todo:
        if c.name in copies:
            source = copies[c.name]
            if is_complete(folder(source), keys[source.name]):
                fields = scenario_fields(study, c.scenario) if c.scenario != source.scenario else None
                copy_cell(folder(source), folder(c), c.threshold, source.name, keys[c.name], fields)
            else:
                failed.append((c.name, f"its source cell {source.name} did not finish"))
    _grid_failures(study, failed, run, len(cells), in_process)
    return {"cells": len(cells), "ran": len(todo), "seconds": time.perf_counter() - t0, "cell_seconds": seconds}


def prepare(study: Study | str, scenarios: list[str] | None = None, cells: bool = False,
            progress: bool = True) -> Study:
    """Make what a notebook needs exist, each stage skipped when its files exist (`stages`, the same path as
    `run`): the dataset (rendered when the study is synthetic), the perception models that `scenarios` use
    (trained, evaluated, every selected frame predicted), the scenarios' scene graphs and, with `cells`, every
    cell of the grid (run in this process: `run_grid(in_process=True)`). `scenarios`: names of the study's
    scenarios, default all of them; `rgb` (the scenario of the image-only methods) needs the dataset only.
    Returns the study. Every notebook calls it first, so that it runs on a fresh clone with its defaults."""
    if not isinstance(study, Study):
        study = load_study(study)
    keep_freed_memory()
    with locks.of_study(study):  # the study's lock: held already inside a run's own cells
        stages(study, None if cells else scenarios, progress=progress)  # the grid needs every scenario
        if cells:
            run_grid(study, progress=progress, in_process=True)
    return study


def unbuilt_graphs(study: Study, scenarios: list[str]) -> dict:
    """``{fold: the scenarios of `scenarios` whose graphs of that fold are not built yet}`` (fold None: the
    release split), folds with nothing to build left out."""
    out = {}
    for fold in study.folds() if scenarios else []:
        at = study.at_fold(fold)
        keys = scenegraphs.scenario_keys(at)
        todo = [n for n in scenarios if not scenegraphs.graphs_path(at, n, keys[n]).exists()]
        if todo:
            out[fold] = todo
    return out


def stages(study: Study, scenarios: list[str] | None = None, progress: bool = True, figures: bool = False,
           times: dict | None = None) -> None:
    """The stages before the cells, in the order data flows, each skipped when its files exist: the dataset, the
    perception models the scenarios' graphs need, the graphs of `scenarios` (default: every scenario, and `rgb`,
    the dataset of the image methods). One path for `prepare` (a notebook) and `run` (the study): with `figures`,
    `run`'s figures of each stage too (the frames mosaic; the perception metrics and Figures 3-4 of every model;
    graph sizes and fidelity), and the stages are announced as ``[i/5]``. `times`: filled with seconds per
    stage (``dataset_s``, ``perception_s``, ``graphs_s``)."""
    def say(line: str) -> None:
        if figures:
            print(line, flush=True)

    times = {} if times is None else times
    names = list(study.scenarios) + [IMAGE_SCENARIO] if scenarios is None else list(scenarios)
    unknown = [n for n in names if n not in study.scenarios and n != IMAGE_SCENARIO]
    if unknown:
        raise StudyError(f"scenario {', '.join(map(repr, unknown))}: not in {study.path} "
                         f"(scenarios: {', '.join(study.scenarios)}, or {IMAGE_SCENARIO} for an image method)")
    wanted = [n for n in names if n in study.scenarios] if study.graph_methods() else []
    todo = unbuilt_graphs(study, wanted)
    built = wanted if figures else sorted({n for ns in todo.values() for n in ns})
    sources = {s for n in built for s in (study.scenarios[n].depth, study.scenarios[n].semantic)}
    models = [] if study.graphs_root else [m for m in study.model_names() if m in sources]
    if models:
        predictions.check_weights(study)  # before any work, the rendering included

    t = time.perf_counter()
    ds = None
    if study.graphs_root:
        say(f"[1/5] dataset: published graphs in {study.graphs_root}")
    elif todo or models or IMAGE_SCENARIO in names or figures:
        say(f"[1/5] dataset: {study.dataset_root}")
        ds = dataset.ensure_dataset(study, progress=progress)
        if figures and not study.extends:
            viz.save_dataset_mosaic(study, paths.figures_dir(study.name) / "frames.png", ds)
        if figures and study.dataset.source == "synth":  # what verify compares first: did the data move?
            write_json(paths.figures_dir(study.name) / digest.FILE, digest.digest(study.dataset_root))
    times["dataset_s"] = time.perf_counter() - t

    t = time.perf_counter()
    rgb = FrameRgb(study.perception.loader_workers)  # the frames' RGB, read once for the networks and the features
    if models:
        say("[2/5] perception")
        # every model for the run's figures (its table lists them all), else those of the graphs to build
        predictions.run(study, progress=progress, only=None if figures else models, dataset=ds, rgb=rgb)
        if figures and not study.extends:  # the paper's Figures 3 and 4 and the training curves, into figures/
            perception_figures.draw_figures(study, dataset=ds)
    else:
        say("[2/5] perception: not needed (ground-truth scenarios only)")
    imagenet = [m for m in study.methods if m in methods.IMAGENET]
    if imagenet and IMAGE_SCENARIO in names:
        say(f"[2/5] perception: ImageNet features of the frames ({', '.join(imagenet)})")
        features.ensure(study, ds, progress=progress, rgb=rgb)
    times["perception_s"] = time.perf_counter() - t

    t = time.perf_counter()
    if wanted:
        say(f"[3/5] graphs: {len(wanted)} scenarios")
        for fold, unbuilt in todo.items():
            scenegraphs.build_all(study.at_fold(fold), unbuilt, progress=progress)
        if figures and study.folds() != [None]:
            say("[3/5] graph sizes and fidelity: per fold, in the report's folds.md")
        elif figures:
            graph_sizes.write_graph_sizes(study)  # graph_sizes.md / .csv: nodes and edges per scenario and threshold
            fidelity.write(study)  # fidelity.md / .csv: the ground-truth graphs beside real Hypersim's statistics
    times["graphs_s"] = time.perf_counter() - t


def write_run_record(study: Study, times: dict, path: Path) -> None:
    """How long each stage of this run took, and on what machine (docs/benchmarks.md shows it)."""
    import platform

    import torch

    record = {"study": study.name, "stage_seconds": {k[:-2]: round(v, 1) for k, v in times.items()},
              "total_seconds": round(sum(times.values()), 1), "cpus": os.cpu_count(),
              "machine": f"{platform.machine()} {platform.processor()}".strip(), "python": platform.python_version(),
              "torch": torch.__version__, "torch_threads": study.threads, "jobs": study.jobs,
              "date": time.strftime("%Y-%m-%d"), "environment": lockfile.environment_record()}
    write_json(path, record)


def run(study: Study, jobs: int | None = None, progress: bool = True, scheduler: str | None = None) -> dict:
    """All stages of a study, each skipped when its results exist. Returns timings per stage. `scheduler`: the
    address (or scheduler file) of a Dask scheduler whose workers run the cells (`monolib.study.cluster`). Holds the
    study's lock (`monolib.locks`): a second run of the same study waits for this one."""
    with locks.of_study(study):
        return _run(study, jobs, progress, scheduler)


def _run(study: Study, jobs: int | None, progress: bool, scheduler: str | None) -> dict:
    check_notebook_parameters(CELL_NOTEBOOK, {"study", "method", "scenario", "threshold", "seed", "out_dir", "fold"})
    check_notebook_parameters(REPORT_NOTEBOOK, {"study"})
    if scheduler:
        cluster.check(scheduler, study)
    times: dict[str, float] = {}
    stages(study, progress=progress, figures=True, times=times)  # what `prepare` runs for a notebook, and figures

    t = time.perf_counter()
    print("[4/5] cells", flush=True)
    grid_run = run_grid(study, jobs, progress, scheduler=scheduler)
    times["cells_s"] = time.perf_counter() - t

    t = time.perf_counter()
    print("[5/5] report", flush=True)
    execute(REPORT_NOTEBOOK, study.dir / "notebooks" / "report.ipynb", {"study": study.path}, study.cell_timeout)
    times["report_s"] = time.perf_counter() - t
    out = paths.figures_dir(study.name)
    if grid_run["ran"] or not (out / "timings.json").is_file():  # a cached re-run keeps the record of the real run
        write_run_record(study, times, out / "timings.json")
    if study.name in paths.COMMITTED_FIGURES:
        if readme.update():
            print("README.md, docs/: result blocks updated from figures/", flush=True)
    tables = "folds_table1_recall.md, folds_table2_precision.md, intervals.csv" if study.folds_only \
        else "table1_recall.md, table2_precision.md, results.csv"
    print(f"done: tables and figures in {out} ({tables}); executed notebooks in {study.dir / 'notebooks'}", flush=True)
    return times
