"""Which property of the data sets what the edges cost: `monolib data-edits` (`make data-edits`, params/data_edits.yaml
-> figures/data_edits/).

The edge penalty (recall@1 at a threshold minus the same encoder's without edges) differs between the two legs of
the study beyond its intervals: the undirected encoder loses far more on the mini-Hypersim than on the published real
graphs (docs/results.md). Each edit here changes one property of one leg's graphs toward the other leg's value
(`monolib.graphs.edits`), trains the encoders on the edited graphs exactly as a cell does (`gcn.encoder_graph`,
`gcn.train`, `gcn.embed`, `evaluate.evaluate_protocols` with the study's own settings, on the same queries), and
measures the penalty again: a property that sets the penalty moves it toward the other leg's. The edits:

- ``none``: the graphs as they are (the reference every edit is paired with);
- ``label_light``: each label's median brightness relative to the wall's made the other leg's (`edits.relight`);
- ``label_frequency``: a label in more of the graphs than in the other leg's thinned to the other leg's share
  (`edits.thin_label`);
- ``setting_light``: the spread of the settings' light levels (sd of their log brightness once each label's level
  is taken out, `edits.light_effects`) made the other leg's (`edits.spread_setting_light`).

A leg's statistics are measured on the training and validation graphs of its first run (the first fold of a
study split by volume), the other leg's target the same way. Every (leg, edit, method, threshold, seed[, fold]) is a
run whose result file (`runs/data_edits/...json`, atomic, keyed like a cell) makes a rerun resume; the tables
(`monolib.report.data_edits`) pair each run with the edit-free run and the 0 m run of the same fold and seed, on
the same queries: 95% intervals from a bootstrap over runs and, within each, over test settings.
"""
from __future__ import annotations

import dataclasses
import inspect
import logging
import textwrap
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import pandas as pd
import torch
import yaml

from monolib import paths, versions
from monolib.graphs import edits, scenegraphs
from monolib.io import read_json, write_json
from monolib.params import Study, StudyError, key_of, load_study
from monolib.report import data_edits as tables
from monolib.retrieval import evaluate, gcn

log = logging.getLogger(__name__)
EDITS = ("none", "label_light", "label_frequency", "setting_light")


@dataclasses.dataclass
class Leg:
    study: str                          # a study file's name (params/<study>.yaml): its graphs and encoder settings
    folds: Optional[list[int]] = None   # the folds to run (a study split by volume); None: the study's one split


@dataclasses.dataclass
class EditStudy:
    name: str
    path: str
    legs: dict[str, Leg]
    scenario: str
    methods: list[str]
    thresholds: list[float]
    seeds: list[int]
    edits: list[str]


FIELDS = {"name": str, "legs": dict, "scenario": str, "methods": list, "thresholds": list, "seeds": list,
          "edits": list}


def load(path: str | Path) -> EditStudy:
    """The study file of the data edits: every key of `FIELDS`, two legs, known edits; one `StudyError` naming the
    file and the key otherwise."""
    path = Path(path)
    if not path.is_file():
        candidate = paths.ROOT / "params" / f"{path}.yaml"
        if not candidate.is_file():
            raise StudyError(f"{path}: no such study file (nor {candidate})")
        path = candidate
    raw = yaml.safe_load(path.read_text()) or {}
    if not isinstance(raw, dict):
        raise StudyError(f"{path}: expected a mapping of {', '.join(FIELDS)}")
    unknown = sorted(set(raw) - set(FIELDS))
    missing = sorted(set(FIELDS) - set(raw))
    if unknown or missing:
        raise StudyError(f"{path}: " + "; ".join(
            ([f"unknown keys {unknown} (known: {', '.join(FIELDS)})"] if unknown else [])
            + ([f"missing keys {missing}"] if missing else [])))
    for key, tp in FIELDS.items():
        if not isinstance(raw[key], tp):
            raise StudyError(f"{path}: {key}: expected a {tp.__name__}, got {raw[key]!r}")
    if len(raw["legs"]) != 2:
        raise StudyError(f"{path}: legs: expected two legs (each edit moves one toward the other), got "
                         f"{sorted(raw['legs'])}")
    legs = {}
    for name, leg in raw["legs"].items():
        if not isinstance(leg, dict) or set(leg) - {"study", "folds"} or "study" not in leg:
            raise StudyError(f"{path}: legs.{name}: expected {{study: NAME, folds: [..] or null}}, got {leg!r}")
        legs[str(name)] = Leg(str(leg["study"]), [int(f) for f in leg["folds"]] if leg.get("folds") else None)
    bad = [e for e in raw["edits"] if e not in EDITS]
    if bad or "none" not in raw["edits"]:
        raise StudyError(f"{path}: edits: {bad or raw['edits']}: expected some of {', '.join(EDITS)}, `none` among "
                         f"them (the reference every edit is paired with)")
    thresholds = [float(t) for t in raw["thresholds"]]
    if any(not t > 0 for t in thresholds):
        raise StudyError(f"{path}: thresholds: {raw['thresholds']}: expected distances > 0 (each is paired with "
                         f"the same encoder at 0 m, which always runs)")
    return EditStudy(str(raw["name"]), str(path), legs, str(raw["scenario"]), [str(m) for m in raw["methods"]],
                     thresholds, [int(s) for s in raw["seeds"]], [str(e) for e in raw["edits"]])


def leg_graphs(study: Study, scenario: str, fold: Optional[int]) -> dict[str, list]:
    """The leg's built graphs of `scenario` (train, val, test) in `fold`."""
    s = study.at_fold(fold)
    if not scenegraphs.graphs_path(s, scenario).is_file():
        raise StudyError(f"{study.path}: the graphs of {scenario} (fold {fold}) are not built: run `monolib study "
                         f"{study.name}` first ({scenegraphs.graphs_path(s, scenario)} is missing)")
    return scenegraphs.load(s, scenario)


def statistics(graphs: dict[str, list]) -> dict[str, Any]:
    """The properties the edits move, measured on the training and validation graphs."""
    seen = graphs["train"] + graphs["val"]
    setting, _ = edits.light_effects(seen)
    return {"light_ratios": edits.light_ratios(seen),
            "label_shares": {lab: edits.label_share(seen, lab) for lab in range(1, 41)},
            "setting_light_sd": float(np.std(list(setting.values()))) if setting else float("nan")}


def apply_edit(edit: str, graphs: dict[str, list], own: dict, other: dict, seed: int = 0) -> dict[str, list]:
    """`graphs` (train, val, test) with one property moved from `own`'s value (`statistics`) to `other`'s."""
    if edit == "none":
        return graphs
    if edit == "label_light":
        factors = edits.light_factors(own["light_ratios"], other["light_ratios"])
        return {k: edits.relight(v, factors) for k, v in graphs.items()}
    if edit == "label_frequency":
        out = graphs
        for lab, share in own["label_shares"].items():
            target = other["label_shares"].get(lab, 0.0)
            if share > target > 0:
                out = {k: edits.thin_label(v, lab, target / share, seed) for k, v in out.items()}
        return out
    if edit == "setting_light":
        names = list(graphs)
        every = edits.spread_setting_light([g for k in names for g in graphs[k]],
                                           other["setting_light_sd"] / own["setting_light_sd"])
        out, start = {}, 0
        for k in names:
            out[k] = every[start:start + len(graphs[k])]
            start += len(graphs[k])
        return out
    raise StudyError(f"edit {edit!r}: unknown (known: {', '.join(EDITS)})")


def run_path(es: EditStudy, leg: str, edit: str, method: str, threshold: float, seed: int,
             fold: Optional[int]) -> Path:
    name = f"{method}__t{paths.threshold_json(threshold)}__s{seed}" + (f"__f{fold}" if fold is not None else "")
    return paths.RUNS / es.name / leg / edit / f"{name}.json"


COMPUTES = ("statistics", "apply_edit", "one_run")  # the functions of this module that decide a run's numbers


def code_version() -> str:
    """What decides a run's numbers: the cells' code version, the edits' module and the functions of this module
    that compute a run (`COMPUTES`; not the loop, the logging, nor the tables of `monolib.report.data_edits`)."""
    own = "\n".join(inspect.getsource(globals()[name]) for name in COMPUTES)
    return key_of({"cells": versions.code_version("cells"), "edits": versions.module_version("graphs.edits"),
                   "runner": versions.source_version(textwrap.dedent(own)),
                   "libraries": versions.library_versions("cells")})


def one_run(study: Study, scenario: str, graphs: dict[str, list], method: str, threshold: float, seed: int) -> dict:
    """Train `method` on the (edited) graphs at `threshold` as a cell does; the paper protocol's hits at rank 1."""
    spec = study.gcn_spec(method)
    projection = study.projection(scenario)
    split = {k: [gcn.encoder_graph(g, threshold, spec, projection) for g in v] for k, v in graphs.items()}
    t = time.perf_counter()
    result = gcn.train(split["train"], split["val"], spec, seed=seed, threads=study.threads,
                       deterministic=study.deterministic)
    emb = gcn.embed(result.model, split["test"]).numpy()
    test = split["test"]
    paper = evaluate.evaluate_protocols(emb, [g.frame for g in test], [g.setting for g in test], study.protocol,
                                        seed)["paper"]
    top = paper.rankings[paper.rankings["rank"] == 1].sort_values("query")
    return {"recall@1": paper.metrics["recall@1"], "queries": top["query"].tolist(),
            "query_settings": top["query_setting"].astype(str).tolist(),
            "hits": (top["match_setting"] == top["query_setting"]).astype(int).tolist(),
            "train_s": round(time.perf_counter() - t, 2), "best_epoch": result.best_epoch}


def run(es: EditStudy, progress: bool = True, only: Optional[str] = None) -> pd.DataFrame:
    """Every run of the study (those done before are read back): one row per run with its recall@1. `only`: the
    runs of that leg alone (two processes, one per leg, use two cores; the tables need both)."""
    if only is not None and only not in es.legs:
        raise StudyError(f"{es.path}: leg {only!r}: not in legs ({', '.join(es.legs)})")
    code = code_version()
    rows = []
    studies = {leg: load_study(spec.study) for leg, spec in es.legs.items()}
    for leg, spec in es.legs.items():
        s = studies[leg]
        if spec.folds and s.protocol.split != "volumes":
            raise StudyError(f"{es.path}: legs.{leg}.folds: {spec.folds}, but {s.path} is not split into folds "
                             f"(protocol.split: {s.protocol.split}); leave folds out")
        unknown = [m for m in es.methods if m != "gcn" and m not in s.variants]
        if unknown:
            raise StudyError(f"{es.path}: methods: {unknown} are not graph encoders of {s.path} (its variants: "
                             f"{', '.join(s.variants)})")
    first = {leg: leg_graphs(studies[leg], es.scenario, (spec.folds or [None])[0]) for leg, spec in es.legs.items()}
    stats = {leg: statistics(g) for leg, g in first.items()}
    cells = [("gcn", 0.0)] + [(m, t) for t in es.thresholds for m in es.methods]
    for leg, spec in es.legs.items():
        if only is not None and leg != only:
            continue
        other = next(o for o in es.legs if o != leg)
        study = studies[leg]
        torch.set_num_threads(study.threads)
        for fold in spec.folds or [None]:
            graphs = first[leg] if fold == (spec.folds or [None])[0] else leg_graphs(study, es.scenario, fold)
            for edit in es.edits:
                edited = None
                for method, threshold in cells:
                    for seed in es.seeds:
                        path = run_path(es, leg, edit, method, threshold, seed, fold)
                        key = key_of({"graphs": scenegraphs.scenario_key(study.at_fold(fold), es.scenario),
                                      "fold": fold, "edit": edit, "own": stats[leg], "other": stats[other],
                                      "encoder": dataclasses.asdict(study.gcn_spec(method)),
                                      "threshold": paths.threshold_json(threshold), "seed": seed,
                                      "protocol": dataclasses.asdict(study.protocol), "threads": study.threads,
                                      "code": code})
                        record = read_json(path) if path.is_file() else None
                        if record is None or record.get("key") != key:
                            if edited is None:
                                edited = apply_edit(edit, graphs, stats[leg], stats[other])
                            record = {"key": key, "leg": leg, "study": study.name, "fold": fold, "edit": edit,
                                      "method": method, "threshold": paths.threshold_json(threshold), "seed": seed,
                                      **one_run(study.at_fold(fold), es.scenario, edited, method, threshold, seed)}
                            write_json(path, record)
                            if progress:
                                log.info("%s %s fold %s %s %s %s m seed %s: recall@1 %.1f", es.name, leg, fold,
                                         edit, method, threshold, seed, record["recall@1"])
                        rows.append(record)
    write_json(paths.RUNS / es.name / "statistics.json", stats)
    return pd.DataFrame(rows)


def main(study_file: str = "data_edits", progress: bool = True, leg: Optional[str] = None) -> Optional[Path]:
    """Run the study (or one `leg` of it) and, with both legs, write its tables: their path (None for one leg)."""
    es = load(study_file)
    t = time.perf_counter()
    frame = run(es, progress, leg)
    if leg is not None:
        log.info("%s: %d runs of %s in %.0f s", es.name, len(frame), leg, time.perf_counter() - t)
        return None
    path = tables.write(es, frame, read_json(paths.RUNS / es.name / "statistics.json"), paths.FIGURES / es.name)
    log.info("%s: %d runs in %.0f s -> %s", es.name, len(frame), time.perf_counter() - t, path)
    return path
