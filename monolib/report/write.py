"""The report stage: merge every cell of a study into Table 1, Table 2, the intervals, the controlled comparisons
and the figures (`write_report`; what ``notebooks/report.ipynb`` and ``monolib study`` call).

The work is split by concern:

- `monolib.report.results`: reading the cells (``cell.json``, ``rankings.csv``, ``protocol.csv``), recomputing the
  metrics from the rankings, checking the protocol, per-query values, the paper's published numbers;
- `monolib.report.bootstrap`: mean and std over seeds, the hierarchical bootstrap (intervals), paired differences;
- `monolib.report.comparisons`: the tables built on the paired bootstrap: thresholds against the best, and the
  controlled comparisons (encoder ablation, dim vs bright, depth scale, protocols);
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
from monolib.report import bootstrap, claims, comparisons, direction, figures, folds, results, tables, training
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
                 n_boot: int = bootstrap.N_BOOT) -> dict[str, Path]:
    """Collect a study's cells and write into `monolib.paths.figures_dir(study)`:

    - ``results.csv``: one row per (method, scenario, threshold, seed, protocol, metric, k) number;
    - ``intervals.csv``: per (method, scenario, threshold, protocol, metric, k) the mean and its 95 % bootstrap
      interval over test settings, queries and seeds (`monolib.report.bootstrap.intervals`, ``n_boot`` resamples, numpy
      seed 0, one resample per protocol);
    - ``threshold_tests.csv``: each threshold against its scenario's best
      (`monolib.report.comparisons.threshold_tests`), per protocol;
    - Table 1 and 2 (md, csv, tex) of the ``paper`` protocol with the intervals and a dagger on thresholds
      significantly below the best, and the same tables of the ``siblings`` protocol (``table1_recall_siblings.*``,
      ``table2_precision_siblings.*``) when the cells have it; scenarios with ``in_tables: false`` are left out of
      the tables and of ``recall_vs_threshold.png``;
    - ``fig_protocols.png`` + ``protocols.{csv,md}``: recall@1 of each method on both protocols
      (`monolib.report.comparisons.protocols_table`;
      when the cells have more than one protocol);
    - ``siblings_confusions.{md,csv}``: per row of the protocols table, where the ``siblings`` queries' top-1
      matches go (own setting, the sibling setting of its family, another family; over seeds;
      `monolib.report.comparisons.siblings_confusions`), when the protocols table has the ``siblings`` protocol;
    - ``recall_vs_threshold.png`` (error bars: the intervals) and ``fig5_matches.png`` (skipped when `rgb_of` is
      None or the study has no `method` cell), ``paper`` protocol;
    - ``encoder_ablation.{md,csv}`` when the study has encoder variants (``paper`` protocol);
    - ``ablation_<method>.{md,csv}`` for each method that variants name in ``ablation_of`` (each of its parts
      switched, against it, on every protocol);
    - ``edge_penalty.{md,csv}``: each graph encoder at every threshold against itself without edges, paired
      (``paper`` protocol), when it has a cell without edges;
    - ``direction.{md,csv}`` when variants of `gcn` change its edges' direction or node order
      (`monolib.report.direction`);
    - ``recall_by_light.png`` + ``light.csv`` when the dataset records dim settings (``monolib_synth.json``;
      ``paper`` protocol);
    - ``recall_vs_depth_scale.png`` + ``depth_scale.csv`` when the study has scenarios with ``depth_scale != 1``
      (``paper`` protocol);
    - ``claims.{md,csv}`` when ``params/claims.yaml`` has claims for the study (`monolib.report.claims`);
    - ``projection.{md,csv}`` when a scenario of the tables has a twin in the other camera of the graph stage
      (`monolib.report.comparisons.projection_table`, ``paper`` protocol); ``colour.{md,csv}`` likewise when one
      has a twin with node colours in the other space (`monolib.report.comparisons.colour_table`).

    `study_name` is a name or a loaded `monolib.params.Study`; `study` (default: ``params/<name>.yaml`` when it
    loads) gives variant descriptions, scenario information and the dataset folder. Labels default to the
    ``scenario_label`` the cells recorded. Returns ``{"results": path, "intervals": path, "table1_md": path, ...}``.
    Raises `monolib.report.results.CellMismatchError` when a cell's ``cell.json`` metrics (the tables' means) are not
    what its ``rankings.csv`` gives (the intervals' per-query values).
    """
    if not isinstance(study_name, (str, Path)):
        study, study_name = study_name, study_name.name
    study_name = str(study_name)
    r = _Report(study_name, study if study is not None else _load_study(study_name), n_boot, method)
    if r.study is not None and r.study.folds_only:  # folds only: every table is over folds
        r.written.update(folds.write(r.study, r.out, n_boot))
        log.info("report of %s (folds only) written to %s", study_name, r.out)
        return r.written
    _write_results(r, scenario_labels)
    _write_intervals(r)
    r.written.update(claims.write(study_name, r.out, r.qv_all, r.iv_all, r.boots, n_boot=n_boot, grid=r.cells))
    _write_tables(r, rgb_of)
    _write_protocols(r)
    if r.qv is None:
        log.info("report of %s written to %s", study_name, r.out)
        return r.written
    _write_ablations(r)
    _write_edge_penalty(r)
    r.written.update(direction.write(r.study, r.out, r.iv, r.labels))
    _write_twins(r)
    _write_light(r)
    _write_depth_scale(r)
    r.written.update(folds.write(r.study, r.out, n_boot))  # a study with folds by volume: its tables over folds
    log.info("report of %s written to %s", study_name, r.out)
    return r.written


class _Report:
    """What the parts of one report share: the study, its cells and numbers, the per-query values and intervals of
    every protocol (``qv_all``, ``iv_all``, ``boots``), those of the ``paper`` protocol that the controlled
    comparisons use (``qv``, ``iv``, ``boot``), the scenarios' information and the files written so far."""

    def __init__(self, study_name: str, study, n_boot: int, method: str):
        self.study_name, self.study, self.n_boot, self.method = study_name, study, n_boot, method
        self.out = paths.figures_dir(study_name)
        # the cells of the study's grid and nothing else: a seed, threshold or method dropped from the study file
        # leaves its cells on disk, out of the tables (without the study file: every cell found)
        self.cells = grid.names(study) if study is not None else None
        self.written: dict[str, Path] = {}
        self.numbers = self.labels = self.info = None
        self.qv_all = self.iv_all = self.tests = self.qv = self.iv = self.boot = None
        self.boots: dict = {}
        self.hidden: set = set()

    def write(self, key: str, name: str, text: str) -> None:
        io.write_text(self.out / name, text)
        self.written[key] = self.out / name


def _write_results(r: _Report, scenario_labels: Optional[Mapping[str, str]]) -> None:
    """``results.csv``, the training figures; the numbers and labels of the study's cells."""
    stale = results.left_out(r.study_name, r.cells) if r.cells is not None else []
    if stale:
        log.warning("%s: %d cells outside the study's grid left out of the report (kept on disk), e.g. %s",
                    results.cells_root(r.study_name), len(stale), stale[0].parent)
    r.numbers = results.collect(r.study_name, r.cells)
    r.labels = {**results.recorded_labels(r.study_name, r.cells),
                **(results.labels_of(r.study) if r.study is not None else {}), **dict(scenario_labels or {})}
    r.write("results", "results.csv", r.numbers.to_csv(index=False, float_format="%.6g", lineterminator="\n"))
    r.written.update(training.write(r.study_name, r.out, r.cells, r.study))
    r.info = results.scenario_info(r.study_name, r.study)
    r.hidden = set(r.info.loc[~r.info["in_tables"].astype(bool), "scenario"])


def _write_intervals(r: _Report) -> None:
    """``intervals.csv`` and ``threshold_tests.csv``, each protocol resampled on its own (nothing paired across
    them); nothing when the cells have no per-query rankings."""
    try:
        r.qv_all = results.query_table(r.study_name, r.cells)
    except FileNotFoundError as exc:
        print(f"{r.study_name}: no per-query rankings, tables without intervals ({exc})")
        return
    ivs, tts = [], []
    for p in results.protocols_in(r.qv_all):
        qp = results.only_protocol(r.qv_all, p)
        r.boots[p] = bootstrap.Bootstrap.for_queries(qp, r.n_boot)
        ivs.append(bootstrap.intervals(qp, r.boots[p]))
        tts.append(comparisons.threshold_tests(qp, ivs[-1], r.boots[p]))
    r.iv_all = results.sort_rows(pd.concat(ivs, ignore_index=True), results.SUMMARY_KEYS)
    r.tests = pd.concat(tts, ignore_index=True)
    r.write("intervals", "intervals.csv", tables.csv_text(r.iv_all))
    r.write("threshold_tests", "threshold_tests.csv", tables.csv_text(r.tests))
    if PAPER in r.boots:  # the controlled comparisons: the paper protocol
        r.qv, r.iv = results.only_protocol(r.qv_all, PAPER), results.only_protocol(r.iv_all, PAPER)
        r.boot = r.boots[PAPER]


def _write_tables(r: _Report, rgb_of: Optional[figures.RgbOf]) -> None:
    """Table 1 and 2 of every protocol, ``recall_vs_threshold.png`` and ``fig5_matches.png``."""
    in_tables = r.numbers[~r.numbers["scenario"].isin(r.hidden)]
    shown = set(in_tables["scenario"])
    cameras = tables.camera_note({str(x.scenario): str(x.projection) for x in r.info.itertuples()
                                  if x.in_tables and x.scenario in shown})
    for p in results.protocols_in(r.numbers):
        note = (tables.protocol_note(p, r.study.protocol if r.study is not None else None) + " " + cameras).strip()
        r.written.update(tables.write_tables(in_tables, r.out, r.labels, r.iv_all, r.tests, r.n_boot, protocol=p,
                                             note=note))
    r.written["recall_vs_threshold"] = figures.fig_recall_vs_threshold(
        in_tables, r.out / "recall_vs_threshold.png", r.method, scenario_labels=r.labels, intervals=r.iv_all)
    if rgb_of is not None and (in_tables["method"] == r.method).any():
        r.written["fig5_matches"] = figures.fig_matches(r.study_name, rgb_of, r.out / "fig5_matches.png", r.method,
                                                        results=in_tables, scenario_labels=r.labels)


def _write_protocols(r: _Report) -> None:
    """``protocols.{csv,md}``, ``fig_protocols.png`` and ``siblings_confusions.{csv,md}`` when the cells have more
    than one protocol."""
    if r.qv_all is None or len(results.protocols_in(r.qv_all)) <= 1:
        print(f"{r.study_name}: one protocol only (protocol.siblings: 0): fig_protocols.png not drawn")
        return
    table = comparisons.protocols_table(r.qv_all, r.iv_all, r.hidden)
    r.write("protocols_csv", "protocols.csv", tables.csv_text(table))
    r.write("protocols_md", "protocols.md", tables.protocols_markdown(table, r.labels, r.n_boot))
    r.written["fig_protocols"] = figures.fig_protocols(table, r.out / "fig_protocols.png", n_boot=r.n_boot)
    sib = table[table["protocol"] == SIBLINGS]
    if len(sib):
        groups = set(zip(sib["method"], sib["scenario"], sib["threshold"]))
        top1 = results.rankings_table(r.study_name, r.cells, groups, protocol=SIBLINGS, max_rank=1)
        conf = comparisons.siblings_confusions(top1, table)
        if len(conf):
            r.write("siblings_confusions_csv", "siblings_confusions.csv", tables.csv_text(conf))
            r.write("siblings_confusions_md", "siblings_confusions.md", tables.confusions_markdown(conf, r.labels))


def _write_ablations(r: _Report) -> None:
    """``encoder_ablation.{md,csv}`` (paper protocol) and ``ablation_<method>.{md,csv}`` for each method whose
    parts variants switch one at a time (every protocol)."""
    ablation = comparisons.encoder_ablation(r.qv, r.iv, r.boot, r.study, base=r.method)
    if len(ablation):
        r.write("encoder_ablation_md", "encoder_ablation.md",
                tables.ablation_markdown(ablation, r.labels, r.method, r.n_boot))
        r.write("encoder_ablation_csv", "encoder_ablation.csv", tables.csv_text(ablation))
    qv_all, iv_all = r.qv_all, r.iv_all
    for base, parts in _ablations_of(r.study).items():
        tabs = {p: comparisons.encoder_ablation(qv_all[qv_all["method"].isin([base, *parts])],
                                               iv_all[iv_all["method"].isin([base, *parts])], r.boots[p], r.study,
                                               base=base, protocol=p) for p in results.protocols_in(qv_all)}
        tabs = {p: t for p, t in tabs.items() if len(t)}
        if tabs:
            md = "\n".join(tables.ablation_markdown(t, r.labels, base, r.n_boot, title=f"Ablation of `{base}`, "
                                                    f"protocol `{p}`: each variant switches one of its parts.")
                           for p, t in tabs.items())
            r.write(f"ablation_{base}_md", f"ablation_{base}.md", md)
            r.write(f"ablation_{base}_csv", f"ablation_{base}.csv",
                    tables.csv_text(pd.concat(tabs.values(), ignore_index=True)))


def _write_edge_penalty(r: _Report) -> None:
    """``edge_penalty.{md,csv}``: each graph encoder's recall@1 at every threshold against its own without edges
    (paper protocol; scenarios of the tables and their twins alike)."""
    table = comparisons.edge_penalty(r.qv, r.iv, r.boot)
    if len(table):
        r.write("edge_penalty_md", "edge_penalty.md", tables.edge_penalty_markdown(table, r.labels, r.n_boot))
        r.write("edge_penalty_csv", "edge_penalty.csv", tables.csv_text(table))


def _write_twins(r: _Report) -> None:
    """``projection.{md,csv}`` and ``colour.{md,csv}``: scenarios against their twins in the other camera or colour
    space (paper protocol)."""
    for axis, table_of, markdown_of in (("projection", comparisons.projection_table, tables.projection_markdown),
                                        ("colour", comparisons.colour_table, tables.colour_markdown)):
        twins = table_of(r.qv, r.iv, r.boot, r.info)
        if len(twins):
            r.write(f"{axis}_md", f"{axis}.md", markdown_of(twins, r.labels, r.n_boot))
            r.write(f"{axis}_csv", f"{axis}.csv", tables.csv_text(twins))


def _write_light(r: _Report) -> None:
    """``light.csv`` and ``recall_by_light.png`` when the dataset records dim settings among the queries."""
    dim_of = results.dim_settings(r.study_name, r.study)
    if dim_of is None:
        print(f"{r.study_name}: no monolib_synth.json with dim settings: recall_by_light.png not drawn")
    elif not any(dim_of.get(s, False) for s in r.qv["setting"].unique()):
        print(f"{r.study_name}: no dim test setting among the queries: recall_by_light.png not drawn")
    else:
        shown = [sc for sc in r.qv["scenario"].unique() if sc not in r.hidden]
        light = comparisons.light_table(r.qv, r.iv, r.boot, dim_of, shown, r.method)
        r.write("light", "light.csv", tables.csv_text(light))
        r.written["recall_by_light"] = figures.fig_recall_by_light(light, r.out / "recall_by_light.png", r.method,
                                                                   n_boot=r.n_boot)


def _write_depth_scale(r: _Report) -> None:
    """``depth_scale.csv`` and ``recall_vs_depth_scale.png`` when the study has scenarios with a depth scale."""
    depth = comparisons.depth_scale_table(r.qv, r.iv, r.boot, r.info, r.method)
    if depth.empty:
        print(f"{r.study_name}: no scenario with depth_scale != 1 (and {r.method} cells): recall_vs_depth_scale.png "
              f"not drawn")
        return
    r.write("depth_scale", "depth_scale.csv", tables.csv_text(depth))
    r.written["recall_vs_depth_scale"] = figures.fig_recall_vs_depth_scale(
        depth, r.out / "recall_vs_depth_scale.png", n_boot=r.n_boot)
