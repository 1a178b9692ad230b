"""The report stage: merge every cell of a study into Table 1, Table 2, the intervals, the controlled comparisons
and the figures (`write_report`; what ``notebooks/report.ipynb`` and ``monolib study`` call).

The work is split by concern:

- `monolib.report.results`: reading the cells (``cell.json``, ``rankings.csv``, ``protocol.csv``), recomputing the metrics
  from the rankings, checking the protocol, per-query values, the paper's published numbers;
- `monolib.report.statistics`: mean and std over seeds, the hierarchical bootstrap (intervals), paired tests (thresholds
  against the best), and the controlled comparisons (encoder ablation, dim vs bright, depth scale, protocols);
- `monolib.report.tables`: Table 1 and 2 in md, csv and TeX, the ablation and protocols tables, number formats;
- `monolib.report.figures`: recall vs threshold, Figure 5 (top-1 matches), recall by light, vs depth scale, by protocol.

Everything reads files the cells wrote, never notebook outputs, and writes through the atomic helpers of
:mod:`monolib.io`, so a re-run on unchanged cells reproduces the same bytes.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Optional

import pandas as pd

from monolib import io, params, paths
from monolib.params import PAPER, SIBLINGS
from monolib.report import figures, folds, results, statistics, tables, training
from monolib.retrieval import grid

log = logging.getLogger(__name__)


# ---- the whole report ------------------------------------------------------------------------------------------

def _load_study(study_name: str):
    """The study of that name from `params/` (None when there is no such file or it does not load)."""
    try:
        return params.load_study(study_name, check_files=False)
    except (params.StudyError, OSError) as exc:
        log.info("report of %s without its study file (%s)", study_name, exc)
        return None


def _ablations_of(study) -> dict[str, list[str]]:
    """{method: the variants of the study that switch one part of it (`Variant.ablation_of`)}."""
    out: dict[str, list[str]] = {}
    for name, v in (getattr(study, "variants", None) or {}).items():
        if v.ablation_of:
            out.setdefault(v.ablation_of, []).append(name)
    return out


def write_report(study_name, rgb_of: Optional[figures.RgbOf] = None,
                 scenario_labels: Optional[Mapping[str, str]] = None, method: str = "gcn", study=None,
                 n_boot: int = statistics.N_BOOT) -> dict[str, Path]:
    """Collect a study's cells and write into `monolib.paths.figures_dir(study)`:

    - ``results.csv``: one row per (method, scenario, threshold, seed, protocol, metric, k) number;
    - ``intervals.csv``: per (method, scenario, threshold, protocol, metric, k) the mean and its 95 % bootstrap
      interval over test settings, queries and seeds (`monolib.report.statistics.intervals`, ``n_boot`` resamples, numpy seed 0, one
      resample per protocol);
    - ``threshold_tests.csv``: each threshold against its scenario's best (`monolib.report.statistics.threshold_tests`), per
      protocol;
    - Table 1 and 2 (md, csv, tex) of the ``paper`` protocol with the intervals and a dagger on thresholds
      significantly below the best, and the same tables of the ``siblings`` protocol (``table1_recall_siblings.*``,
      ``table2_precision_siblings.*``) when the cells have it; scenarios with ``in_tables: false`` are left out of
      the tables and of ``recall_vs_threshold.png``;
    - ``fig_protocols.png`` + ``protocols.{csv,md}``: recall@1 of each method on both protocols
      (`monolib.report.statistics.protocols_table`;
      when the cells have more than one protocol);
    - ``siblings_confusions.{md,csv}``: per row of the protocols table, where the ``siblings`` queries' top-1
      matches go (own setting, the sibling setting of its family, another family; over seeds;
      `monolib.report.statistics.siblings_confusions`), when the protocols table has the ``siblings`` protocol;
    - ``recall_vs_threshold.png`` (error bars: the intervals) and ``fig5_matches.png`` (skipped when `rgb_of` is
      None or the study has no `method` cell), ``paper`` protocol;
    - ``encoder_ablation.{md,csv}`` when the study has encoder variants (``paper`` protocol);
    - ``ablation_<method>.{md,csv}`` for each method that variants name in ``ablation_of`` (each of its parts
      switched, against it, on every protocol);
    - ``recall_by_light.png`` + ``light.csv`` when the dataset records dim settings (``monolib_synth.json``;
      ``paper`` protocol);
    - ``recall_vs_depth_scale.png`` + ``depth_scale.csv`` when the study has scenarios with ``depth_scale != 1``
      (``paper`` protocol);
    - ``projection.{md,csv}`` when a scenario of the tables has a twin in the other camera of the graph stage
      (`monolib.report.statistics.projection_table`, ``paper`` protocol); ``colour.{md,csv}`` likewise when one
      has a twin with node colours in the other space (`monolib.report.statistics.colour_table`).

    `study_name` is a name or a loaded `monolib.params.Study`; `study` (default: ``params/<name>.yaml`` when it
    loads) gives variant descriptions, scenario information and the dataset folder. Labels default to the
    ``scenario_label`` the cells recorded. Returns ``{"results": path, "intervals": path, "table1_md": path, ...}``.
    Raises `monolib.report.results.CellMismatchError` when a cell's ``cell.json`` metrics (the tables' means) are not what
    its ``rankings.csv`` gives (the intervals' per-query values).
    """
    if not isinstance(study_name, (str, Path)):
        study, study_name = study_name, study_name.name
    study_name = str(study_name)
    if study is None:
        study = _load_study(study_name)
    out = paths.figures_dir(study_name)
    # the cells of the study's grid and nothing else: a seed, threshold or method dropped from the study file
    # leaves its cells on disk, out of the tables (without the study file: every cell found)
    cells = grid.names(study) if study is not None else None
    stale = results.left_out(study_name, cells) if cells is not None else []
    if stale:
        log.warning("%s: %d cells outside the study's grid left out of the report (kept on disk), e.g. %s",
                    results.cells_root(study_name), len(stale), stale[0].parent)
    numbers = results.collect(study_name, cells)
    labels = {**results.recorded_labels(study_name, cells), **(results.labels_of(study) if study is not None else {}),
              **dict(scenario_labels or {})}
    written: dict[str, Path] = {}
    io.write_text(out / "results.csv", numbers.to_csv(index=False, float_format="%.6g", lineterminator="\n"))
    written["results"] = out / "results.csv"
    written.update(training.write(study_name, out, cells, study))

    try:
        qv_all = results.query_table(study_name, cells)
    except FileNotFoundError as exc:
        print(f"{study_name}: no per-query rankings, tables without intervals ({exc})")
        qv_all = None
    protos = results.protocols_in(numbers)
    iv_all = tests = qv = iv = boot = None
    if qv_all is not None:
        ivs, tts, boots = [], [], {}
        for p in results.protocols_in(qv_all):  # each protocol resampled on its own: nothing paired across them
            qp = results.only_protocol(qv_all, p)
            boots[p] = statistics.Bootstrap.for_queries(qp, n_boot)
            ivs.append(statistics.intervals(qp, boots[p]))
            tts.append(statistics.threshold_tests(qp, ivs[-1], boots[p]))
        iv_all = results.sort_rows(pd.concat(ivs, ignore_index=True), results.SUMMARY_KEYS)
        tests = pd.concat(tts, ignore_index=True)
        io.write_text(out / "intervals.csv", tables.csv_text(iv_all))
        written["intervals"] = out / "intervals.csv"
        io.write_text(out / "threshold_tests.csv", tables.csv_text(tests))
        written["threshold_tests"] = out / "threshold_tests.csv"
        if PAPER in boots:  # the controlled comparisons below: the paper protocol
            qv, iv, boot = results.only_protocol(qv_all, PAPER), results.only_protocol(iv_all, PAPER), boots[PAPER]

    info = results.scenario_info(study_name, study)
    hidden = set(info.loc[~info["in_tables"].astype(bool), "scenario"])
    in_tables = numbers[~numbers["scenario"].isin(hidden)]
    shown = set(in_tables["scenario"])
    cameras = tables.camera_note({str(r.scenario): str(r.projection) for r in info.itertuples()
                                  if r.in_tables and r.scenario in shown})
    for p in protos:
        note = (tables.protocol_note(p, study.protocol if study is not None else None) + " " + cameras).strip()
        written.update(tables.write_tables(in_tables, out, labels, iv_all, tests, n_boot, protocol=p, note=note))
    written["recall_vs_threshold"] = figures.fig_recall_vs_threshold(in_tables, out / "recall_vs_threshold.png",
                                                                     method, scenario_labels=labels, intervals=iv_all)
    if rgb_of is not None and (in_tables["method"] == method).any():
        written["fig5_matches"] = figures.fig_matches(study_name, rgb_of, out / "fig5_matches.png", method,
                                                      results=in_tables, scenario_labels=labels)
    if qv_all is not None and len(results.protocols_in(qv_all)) > 1:
        table = statistics.protocols_table(qv_all, iv_all, hidden)
        io.write_text(out / "protocols.csv", tables.csv_text(table))
        io.write_text(out / "protocols.md", tables.protocols_markdown(table, labels, n_boot))
        written["protocols_csv"], written["protocols_md"] = out / "protocols.csv", out / "protocols.md"
        written["fig_protocols"] = figures.fig_protocols(table, out / "fig_protocols.png", n_boot=n_boot)
        sib = table[table["protocol"] == SIBLINGS]
        if len(sib):
            groups = set(zip(sib["method"], sib["scenario"], sib["threshold"]))
            top1 = results.rankings_table(study_name, cells, groups, protocol=SIBLINGS, max_rank=1)
            conf = statistics.siblings_confusions(top1, table)
            if len(conf):
                io.write_text(out / "siblings_confusions.csv", tables.csv_text(conf))
                io.write_text(out / "siblings_confusions.md", tables.confusions_markdown(conf, labels))
                written["siblings_confusions_csv"] = out / "siblings_confusions.csv"
                written["siblings_confusions_md"] = out / "siblings_confusions.md"
    else:
        print(f"{study_name}: one protocol only (protocol.siblings: 0): fig_protocols.png not drawn")

    if qv is None:
        log.info("report of %s written to %s", study_name, out)
        return written
    ablation = statistics.encoder_ablation(qv, iv, boot, study, base=method)
    if len(ablation):
        io.write_text(out / "encoder_ablation.md", tables.ablation_markdown(ablation, labels, method, n_boot))
        io.write_text(out / "encoder_ablation.csv", tables.csv_text(ablation))
        written["encoder_ablation_md"] = out / "encoder_ablation.md"
        written["encoder_ablation_csv"] = out / "encoder_ablation.csv"

    for base, parts in _ablations_of(study).items():  # a method's parts switched one at a time, both protocols
        tabs = {p: statistics.encoder_ablation(qv_all[qv_all["method"].isin([base, *parts])],
                                               iv_all[iv_all["method"].isin([base, *parts])], boots[p], study,
                                               base=base, protocol=p) for p in results.protocols_in(qv_all)}
        tabs = {p: t for p, t in tabs.items() if len(t)}
        if tabs:
            md = "\n".join(tables.ablation_markdown(t, labels, base, n_boot, title=f"Ablation of `{base}`, protocol "
                                                    f"`{p}`: each variant switches one of its parts.")
                           for p, t in tabs.items())
            io.write_text(out / f"ablation_{base}.md", md)
            io.write_text(out / f"ablation_{base}.csv", tables.csv_text(pd.concat(tabs.values(), ignore_index=True)))
            written[f"ablation_{base}_md"], written[f"ablation_{base}_csv"] = (out / f"ablation_{base}.md",
                                                                               out / f"ablation_{base}.csv")

    for axis, table_of, markdown_of in (("projection", statistics.projection_table, tables.projection_markdown),
                                        ("colour", statistics.colour_table, tables.colour_markdown)):
        twins = table_of(qv, iv, boot, info)
        if len(twins):
            io.write_text(out / f"{axis}.md", markdown_of(twins, labels, n_boot))
            io.write_text(out / f"{axis}.csv", tables.csv_text(twins))
            written[f"{axis}_md"], written[f"{axis}_csv"] = out / f"{axis}.md", out / f"{axis}.csv"

    dim_of = results.dim_settings(study_name, study)
    if dim_of is None:
        print(f"{study_name}: no monolib_synth.json with dim settings: recall_by_light.png not drawn")
    elif not any(dim_of.get(s, False) for s in qv["setting"].unique()):
        print(f"{study_name}: no dim test setting among the queries: recall_by_light.png not drawn")
    else:
        shown = [sc for sc in qv["scenario"].unique() if sc not in hidden]
        light = statistics.light_table(qv, iv, boot, dim_of, shown, method)
        io.write_text(out / "light.csv", tables.csv_text(light))
        written["light"] = out / "light.csv"
        written["recall_by_light"] = figures.fig_recall_by_light(light, out / "recall_by_light.png", method,
                                                                 n_boot=n_boot)

    depth = statistics.depth_scale_table(qv, iv, boot, info, method)
    if depth.empty:
        print(f"{study_name}: no scenario with depth_scale != 1 (and {method} cells): recall_vs_depth_scale.png "
              f"not drawn")
    else:
        io.write_text(out / "depth_scale.csv", tables.csv_text(depth))
        written["depth_scale"] = out / "depth_scale.csv"
        written["recall_vs_depth_scale"] = figures.fig_recall_vs_depth_scale(depth, out / "recall_vs_depth_scale.png",
                                                                             n_boot=n_boot)
    written.update(folds.write(study, out, n_boot))  # a study with folds by volume: its tables over folds
    log.info("report of %s written to %s", study_name, out)
    return written
