"""The results of a study's cells: reading the cell files, recomputing the metrics from the rankings, checking the
protocol, and the paper's published numbers.

Everything here reads files the cells wrote (``runs/<study>/cells/<method>/<scenario>__t<threshold>__s<seed>/``:
``cell.json``, ``rankings.csv``, ``protocol.csv``), never notebook outputs.

Metric definitions (the design's protocol)
------------------------------------------
A query's candidates are its own setting's positives plus every frame of the protocol's other settings.
``recall@k``: share of queries with at least one frame of their own setting in the top k.
``precision@k``: mean over queries of (own-setting frames in the top k) / k. Values in percent.
`recompute_metrics` computes them from a cell's ``rankings.csv``; `query_table` gives the per-query values behind
them (what the bootstrap of `monolib.report.bootstrap` resamples) and checks that their means are the metrics the cell
recorded in ``cell.json`` (`CellMismatchError` when not).

Protocols
---------
A cell evaluates one trained encoder on two protocols (`monolib.retrieval.evaluate.evaluate_protocols`): ``paper`` (test
settings of different families: the paper's protocol, the headline Tables 1-2) and ``siblings`` (pairs of settings
of one family, when the study has them). Every per-query table (``results.csv``, ``intervals.csv``, ...) has a
``protocol`` column. A cell written before there were two protocols (flat ``metrics``, rankings without
``protocol``) reads as ``paper``.

Reference numbers
-----------------
``monolib/resources/paper_tables.csv`` is a transcription of the paper's published Table 1 (recall@1/5/10) and
Table 2 (precision@2/4/6) as printed in the paper (columns ``scenario, threshold, metric, k, value, source``;
thresholds ``1, 2, 5, 10, inf``; values in percent). They are the paper's single-run numbers, not ours. Note that
the paper's own Table 1 is not monotone in k for Scenario 4 at 5 m (recall@5 87.5 > recall@10 86.3), which is
impossible for recall over one fixed ranking; it is transcribed as printed (`paper_tables`).
"""
from __future__ import annotations

import logging
import math
import re
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd

from monolib import io, paths
from monolib.data.protocols import family
from monolib.methods import METHODS
from monolib.params import (  # the test protocols (monolib.params: no torch import here)
    PAPER, PROTOCOLS as PROTOCOL_ORDER, SIBLINGS
)
from monolib.retrieval import metrics as cell_metrics_mod

log = logging.getLogger(__name__)

INF = math.inf
METRICS = ("recall", "precision")
RESULT_COLUMNS = ["method", "scenario", "threshold", "seed", "protocol", "metric", "k", "value"]
SUMMARY_KEYS = ["method", "scenario", "threshold", "protocol", "metric", "k"]
RANKING_COLUMNS = ["query", "query_setting", "rank", "match", "match_setting", "distance"]
PROTOCOL_COLUMNS = ["frame", "setting", "role"]
QUERY_KEYS = ["method", "scenario", "threshold", "seed", "protocol", "setting", "query"]
FOLD_CELL = re.compile(r"__f\d+$")  # a fold's cell (folds by volume): read by `monolib.report.folds`, not here
IMAGE_SCENARIO = "rgb"          # the scenario name image-only baselines are written under
METRIC_TOLERANCE = 1e-6         # percent: a recorded metric and its recomputation from the rankings agree within


class ProtocolError(ValueError):
    """A cell's rankings break the evaluation protocol; the message names the query and the match."""


class CellMismatchError(ValueError):
    """A cell's ``cell.json`` metrics are not what its ``rankings.csv`` gives; the message names the cell."""


# ---- small helpers ---------------------------------------------------------------------------------------------

def natural_key(text: str):
    """'s10' after 's2': digits compared as numbers."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(text))]


def threshold_value(value) -> float:
    """1 / 1.0 / '1' -> 1.0; 'inf' / 'Infinity' / inf -> inf."""
    return float(value) + 0.0


def method_order(methods) -> list[str]:
    """The methods in the order of the registry (`monolib.methods.METHODS`), unknown ones after, by name."""
    registry = list(METHODS)
    return sorted(set(methods), key=lambda m: (registry.index(m) if m in registry else len(registry), m))


def protocol_rank(name: str):
    return (PROTOCOL_ORDER.index(name), "") if name in PROTOCOL_ORDER else (len(PROTOCOL_ORDER), str(name))


def protocols_in(frame: pd.DataFrame) -> list[str]:
    """The protocols present in a frame with a ``protocol`` column, paper first."""
    return sorted(frame["protocol"].unique(), key=protocol_rank) if "protocol" in frame.columns else [PAPER]


def only_protocol(frame: Optional[pd.DataFrame], protocol: str) -> Optional[pd.DataFrame]:
    """The rows of one protocol (a frame without a ``protocol`` column holds the paper protocol only)."""
    if frame is None:
        return None
    if "protocol" not in frame.columns:
        return frame if protocol == PAPER else frame.iloc[0:0]
    return frame[frame["protocol"] == protocol]


def with_protocol(frame: pd.DataFrame) -> pd.DataFrame:
    """The frame with a ``protocol`` column (``paper`` when it has none)."""
    return frame if "protocol" in frame.columns else frame.assign(protocol=PAPER)


def split_protocols(rankings: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """``{protocol: its rows}`` of a cell's ``rankings.csv`` or ``protocol.csv`` (paper first); a file without a
    ``protocol`` column (a cell of one protocol) is ``{"paper": all rows}``."""
    if "protocol" not in rankings.columns:
        return {PAPER: rankings}
    return {p: rankings[rankings["protocol"] == p].reset_index(drop=True) for p in protocols_in(rankings)}


def one_protocol_only(frame: pd.DataFrame, what: str) -> None:
    if "protocol" in frame.columns and frame["protocol"].nunique() > 1:
        raise ValueError(f"{what}: rows of protocols {protocols_in(frame)} together; select one (split_protocols)")


def cell_metrics(cell: Mapping) -> dict[str, dict[str, float]]:
    """``{protocol: {metric: value}}`` of a cell.json (flat ``metrics`` of an older cell: the paper protocol)."""
    m = cell["metrics"]
    if any(isinstance(v, Mapping) for v in m.values()):
        return {str(p): dict(v) for p, v in sorted(m.items(), key=lambda kv: protocol_rank(kv[0]))}
    return {PAPER: dict(m)}


def is_image(method: str, scenario: str) -> bool:
    """Whether a method is an image-only baseline (no scene graph)."""
    if method in METHODS:
        return METHODS[method][0] == "image"
    return scenario == IMAGE_SCENARIO


def cells_root(study_name: str) -> Path:
    return paths.study_dir(study_name) / "cells"


def sort_rows(df: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    """Stable sort with the report's orders: scenarios naturally (s2 before s10), methods as registered, protocols
    paper first."""
    def key(col: pd.Series):
        if col.name == "scenario":
            return col.map(lambda s: tuple((0, x, "") if isinstance(x, int) else (1, 0, x) for x in natural_key(s)))
        if col.name == "method":
            order = method_order(col.unique())
            return col.map(order.index)
        if col.name == "protocol":
            return col.map(protocol_rank)
        return col

    return df.sort_values(by, key=key, kind="mergesort").reset_index(drop=True)


# ---- collect ---------------------------------------------------------------------------------------------------

def cell_files(study_name: str, grid: Optional[Collection[str]] = None) -> list[Path]:
    """Every ``cell.json`` of a study, sorted; with `grid` (cell names ``method/scenario__t<t>__s<seed>``,
    `monolib.retrieval.grid.names`) only the cells of the grid."""
    files = sorted(cells_root(study_name).glob("*/*/cell.json"))
    if grid is None:
        return files
    return [f for f in files if f"{f.parent.parent.name}/{f.parent.name}" in grid]


def left_out(study_name: str, grid: Collection[str]) -> list[Path]:
    """The ``cell.json`` files of a study's folder outside its grid (a seed, threshold, scenario or method no
    longer in the study file): kept on disk, left out of every table. The folds' cells are not counted (their
    tables: `monolib.report.folds`)."""
    inside = set(cell_files(study_name, grid))
    return [f for f in cell_files(study_name) if f not in inside and not FOLD_CELL.search(f.parent.name)]


def read_rankings(cell: Path) -> pd.DataFrame:
    """The ``rankings.csv`` of a cell folder."""
    f = cell / "rankings.csv"
    if not f.is_file():
        raise FileNotFoundError(f"{f}: no rankings; is the cell finished?")
    return pd.read_csv(f)


def collect(study_name: str, grid: Optional[Collection[str]] = None) -> pd.DataFrame:
    """All cells of a study (with `grid`: the cells of the grid only, see `cell_files`) in long format: one row
    per number.

    Columns ``method, scenario, threshold (float, inf for 'inf'), seed, protocol ('paper'|'siblings'), metric
    ('recall'|'precision'), k, value`` (percent), sorted by method, scenario (natural order), threshold, seed,
    protocol, metric, k. Raises FileNotFoundError when the study has no cell yet.
    """
    files = cell_files(study_name, grid)
    if not files:
        raise FileNotFoundError(f"{cells_root(study_name)}: no cell.json found{' of the grid' if grid else ''}; "
                                "run the study's cells first")
    rows = []
    for f in files:
        cell = io.read_json(f)
        try:
            base = (str(cell["method"]), str(cell["scenario"]), threshold_value(cell["threshold"]), int(cell["seed"]))
            per_protocol = cell_metrics(cell)
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise ValueError(f"{f}: not a valid cell.json ({exc!r})") from exc
        for protocol, metrics in per_protocol.items():
            for name, value in metrics.items():
                metric, _, k = name.partition("@")
                if metric not in METRICS or not k.isdigit():
                    continue
                rows.append((*base, protocol, metric, int(k), float(value)))
    df = pd.DataFrame(rows, columns=RESULT_COLUMNS)
    return sort_rows(df, ["method", "scenario", "threshold", "seed", "protocol", "metric", "k"])


def recorded_labels(study_name: str, grid: Optional[Collection[str]] = None) -> dict[str, str]:
    """``{scenario: label}`` as the cells recorded them (``scenario_label`` in cell.json)."""
    out: dict[str, str] = {}
    for f in cell_files(study_name, grid):
        cell = io.read_json(f)
        if cell.get("scenario_label"):
            out.setdefault(str(cell["scenario"]), str(cell["scenario_label"]))
    return dict(sorted(out.items(), key=lambda kv: natural_key(kv[0])))


def labels_of(study) -> dict[str, str]:
    """``{scenario: label}`` from a loaded study (`monolib.params.Study`)."""
    return {name: (sc.label or name) for name, sc in study.scenarios.items()}


def scenario_info(study_name: str, study=None) -> pd.DataFrame:
    """``scenario, depth, semantic, depth_scale, in_tables, label, projection, colour`` of every scenario: from the
    study when given, else from what the cells recorded (``depth``, ``semantic``, ``depth_scale`` (default 1),
    ``in_tables`` (default True), ``projection`` (default ``exact``: the one camera of cells that do not record it),
    ``colour`` (default ``tonemapped``, likewise))."""
    cols = ["scenario", "depth", "semantic", "depth_scale", "in_tables", "label", "projection", "colour"]
    rows = []
    if study is not None:
        for name, sc in study.scenarios.items():
            rows.append((name, sc.depth, sc.semantic, float(sc.depth_scale), bool(sc.in_tables), sc.label or name,
                         study.projection(name), study.colour(name)))
    else:
        seen = set()
        for f in cell_files(study_name):
            cell = io.read_json(f)
            name = str(cell.get("scenario"))
            if name in seen or name == IMAGE_SCENARIO or cell.get("depth") is None:
                continue
            seen.add(name)
            rows.append((name, str(cell.get("depth")), str(cell.get("semantic")),
                         float(cell.get("depth_scale") or 1.0), bool(cell.get("in_tables", True)),
                         str(cell.get("scenario_label") or name), str(cell.get("projection") or "exact"),
                         str(cell.get("colour") or "tonemapped")))
    out = pd.DataFrame(rows, columns=cols)
    return out.sort_values("scenario", key=lambda c: c.map(natural_key), kind="mergesort").reset_index(drop=True)


def dim_settings(study_name: str, study=None) -> Optional[dict[str, bool]]:
    """``{setting: dim}`` from the synthetic dataset's ``monolib_synth.json``; None when there is none (a real
    Hypersim download, or a study without a rendered dataset)."""
    root = study.dataset_root if study is not None else paths.study_dir(study_name) / "dataset"
    f = Path(root) / "monolib_synth.json"
    if not f.is_file():
        return None
    return {str(s["name"]): bool(s.get("dim", False)) for s in io.read_json(f).get("settings", [])}


# ---- recomputing the metrics from the rankings -----------------------------------------------------------------

def check_columns(df: pd.DataFrame, columns: list[str], what: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what}: missing columns {missing} (have {list(df.columns)})")


def hit_matrix(rankings: pd.DataFrame) -> tuple[pd.Index, np.ndarray]:
    """(queries, hits) of the rankings of one protocol (`split_protocols`), their columns checked: the cells' own
    definition (`monolib.retrieval.metrics.hit_matrix`)."""
    check_columns(rankings, RANKING_COLUMNS, "rankings")
    one_protocol_only(rankings, "rankings")
    return cell_metrics_mod.hit_matrix(rankings)


def recompute_metrics(rankings: pd.DataFrame, recall_k, precision_k,
                      positives_per_setting: int | Mapping[str, int] | pd.Series | None = None) -> dict[str, float]:
    """recall@k and precision@k (percent) recomputed from a cell's ``rankings.csv`` (one protocol's rows), its
    columns checked: the cells' own definition (`monolib.retrieval.metrics.metrics_from_rankings`).

    ``positives_per_setting`` None (default, the paper's definition): precision@k divides by k. Given (one number,
    or a mapping setting -> number of positives), it divides by ``min(k, positives of the query's setting)``, the
    best reachable share when a setting has fewer positives than k. Raises ValueError when a k exceeds the
    depth of the rankings (the cells store the top 10).
    """
    check_columns(rankings, RANKING_COLUMNS, "rankings")
    one_protocol_only(rankings, "rankings")
    return cell_metrics_mod.metrics_from_rankings(rankings, recall_k, precision_k, positives_per_setting)


def check_protocol(rankings: pd.DataFrame, protocol: pd.DataFrame, positives: Optional[int] = None) -> dict:
    """Raise `ProtocolError` when a cell's rankings break the protocol drawn in its ``protocol.csv``.

    Checked: every ranked query is a protocol query of the setting it claims; settings agree with frame keys;
    (query, rank) and (query, match) are unique; no query retrieves itself; a candidate of the query's own setting
    is one of that setting's positives (never another query, nor a frame outside the draw); every candidate is of
    one of the protocol's settings; no setting has more than ``positives`` positives (when given). One
    protocol's rows (`split_protocols`; `check_protocols` checks every protocol of a cell). Returns counts
    ``{"queries", "settings", "positives"}``.
    """
    check_columns(rankings, RANKING_COLUMNS, "rankings")
    check_columns(protocol, PROTOCOL_COLUMNS, "protocol")
    one_protocol_only(rankings, "rankings")
    one_protocol_only(protocol, "protocol")
    if "protocol" in rankings.columns and "protocol" in protocol.columns and len(rankings) and len(protocol) \
            and rankings["protocol"].iloc[0] != protocol["protocol"].iloc[0]:
        raise ProtocolError(f"rankings of protocol {rankings['protocol'].iloc[0]!r} checked against the draw of "
                            f"{protocol['protocol'].iloc[0]!r}")

    def fail(mask: pd.Series, msg: str, frame: pd.DataFrame = rankings):
        if mask.any():
            row = frame[mask.to_numpy()].iloc[0]
            raise ProtocolError(f"{msg} ({int(mask.sum())} rows; first: {row.to_dict()})")

    roles = protocol["role"].astype(str)
    fail(~roles.isin(["query", "positive"]), "protocol: role must be 'query' or 'positive'", protocol)
    fail(protocol["frame"].duplicated(), "protocol: a frame is listed twice", protocol)
    fail(protocol["frame"].astype(str).str.split("/").str[0] != protocol["setting"].astype(str),
         "protocol: a frame's key does not start with its setting", protocol)
    counts = protocol[roles == "positive"].groupby("setting").size()
    if positives is not None and (counts > positives).any():
        bad = counts[counts > positives]
        raise ProtocolError(f"protocol: settings with more than {positives} positives: {bad.to_dict()}")

    role_of = protocol.set_index("frame")["role"]
    setting_of = protocol.set_index("frame")["setting"]
    q_role = rankings["query"].map(role_of)
    fail(q_role != "query", "rankings: a ranked query is not a query of the protocol")
    fail(rankings["query"].map(setting_of) != rankings["query_setting"],
         "rankings: query_setting disagrees with the protocol")
    fail(rankings["match"].astype(str).str.split("/").str[0] != rankings["match_setting"].astype(str),
         "rankings: match_setting disagrees with the match's frame key")
    fail(rankings.duplicated(["query", "rank"]), "rankings: a (query, rank) pair appears twice")
    fail(rankings.duplicated(["query", "match"]), "rankings: a query retrieves the same frame twice")
    fail(rankings["match"] == rankings["query"], "rankings: a query retrieves itself")
    fail(~rankings["match_setting"].isin(protocol["setting"]), "rankings: a match is not of the protocol's settings")
    own = rankings["match_setting"] == rankings["query_setting"]
    m_role = rankings["match"].map(role_of)
    fail(own & (m_role == "query"), "rankings: a query retrieves another query of its own setting")
    fail(own & (m_role != "positive"), "rankings: a query retrieves a frame of its own setting outside the positives")
    return {"queries": int(rankings["query"].nunique()), "settings": int(protocol["setting"].nunique()),
            "positives": int((roles == "positive").sum())}


def check_protocols(rankings: pd.DataFrame, protocol: pd.DataFrame, positives: Optional[int] = None,
                    settings: Optional[Mapping[str, int]] = None, families: bool = True) -> dict[str, dict]:
    """`check_protocol` for every protocol of a cell (``rankings.csv`` and ``protocol.csv`` with their
    ``protocol`` column), and the protocols' shapes: ``paper``'s settings are all of different families
    (``ai_VVV``) unless `families` is false (`Protocol.families`: real data, where ``paper`` takes its settings in
    turn from fewer families), ``siblings``' settings are pairs of one family; with `settings` (``{protocol: number of
    settings}``) each protocol has that many. Both files must hold the same protocols.
    Returns ``{protocol: counts}``."""
    ranked, drawn = split_protocols(rankings), split_protocols(protocol)
    if list(ranked) != list(drawn):
        raise ProtocolError(f"rankings hold protocols {list(ranked)}, protocol.csv {list(drawn)}")
    out = {}
    for name, r in ranked.items():
        d = drawn[name]
        out[name] = check_protocol(r, d, positives)
        names = sorted(d["setting"].astype(str).unique())
        fams = pd.Series(names).map(family).value_counts()
        if name == PAPER and families and (fams > 1).any():
            raise ProtocolError(f"protocol {name}: settings of one family: "
                                f"{sorted(n for n in names if fams[family(n)] > 1)}")
        if name == SIBLINGS and (fams != 2).any():
            raise ProtocolError(f"protocol {name}: families without exactly 2 settings: "
                                f"{sorted(fams[fams != 2].index)}")
        if settings is not None and name in settings and len(names) != settings[name]:
            raise ProtocolError(f"protocol {name}: {len(names)} settings, {settings[name]} expected")
    if settings is not None and set(settings) != set(out):
        raise ProtocolError(f"protocols {list(out)}, expected {list(settings)}")
    return out


# ---- per-query values ------------------------------------------------------------------------------------------

metric_columns = cell_metrics_mod.metric_names  # recall@k then precision@k: the keys of a cell's metrics


def split_metric(col: str) -> tuple[str, int]:
    """'recall@5' -> ('recall', 5)."""
    metric, _, k = col.partition("@")
    return metric, int(k)


def metric_cols(frame: pd.DataFrame) -> list[str]:
    """The metric columns of a frame (``recall@k``, ``precision@k``), recall first, by k."""
    cols = [c for c in frame.columns if "@" in str(c)]
    return sorted(cols, key=lambda c: (METRICS.index(split_metric(c)[0]), split_metric(c)[1]))


def per_query_values(rankings: pd.DataFrame, recall_k, precision_k) -> pd.DataFrame:
    """One row per query of a cell: ``query, setting`` and one column per metric (``recall@1``: 100 when a frame
    of the query's setting is in the top k, else 0; ``precision@6``: 100 x own-setting frames in the top k / k).
    Their means over queries are `recompute_metrics` (the paper's definitions)."""
    queries, hits = hit_matrix(rankings)
    ks = [int(k) for k in recall_k] + [int(k) for k in precision_k]
    if ks and max(ks) > hits.shape[1]:
        raise ValueError(f"rankings: k={max(ks)} needs the top {max(ks)}, the rankings hold the top {hits.shape[1]}")
    found = np.cumsum(hits, axis=1)
    setting = rankings.drop_duplicates("query").set_index("query")["query_setting"].reindex(queries)
    out = pd.DataFrame({"query": np.asarray(queries, dtype=object), "setting": setting.to_numpy(dtype=object)})
    for k in recall_k:
        out[f"recall@{int(k)}"] = 100.0 * (found[:, int(k) - 1] > 0)
    for k in precision_k:
        out[f"precision@{int(k)}"] = 100.0 * found[:, int(k) - 1] / int(k)
    return out


def check_recorded_metrics(cell: Path, protocol: str, recorded: Mapping[str, float], values: pd.DataFrame) -> None:
    """Raise `CellMismatchError` when a metric a cell recorded (``cell.json``) is not the mean of its per-query
    values from ``rankings.csv`` (`per_query_values`): the tables' means come from the first, their intervals
    from the second, so the two must be one number."""
    for col in metric_cols(values):
        again = float(values[col].mean())
        if col in recorded and not abs(float(recorded[col]) - again) <= METRIC_TOLERANCE:
            raise CellMismatchError(f"{cell}: {protocol} {col} is {float(recorded[col])!r} in cell.json but "
                                    f"{again!r} from rankings.csv: the cell's files disagree")


def query_table(study_name: str, grid: Optional[Collection[str]] = None) -> pd.DataFrame:
    """Per-query values of every cell of a study: ``method, scenario, threshold, seed, protocol, setting, query``
    and one column per metric the cell recorded (see `per_query_values`), read from each cell's ``rankings.csv``,
    protocol by protocol. Raises `CellMismatchError` when a cell's recorded metrics are not the means of its
    per-query values (`check_recorded_metrics`)."""
    parts = []
    for f in cell_files(study_name, grid):
        cell = io.read_json(f)
        try:
            recorded = cell_metrics(cell)
            by_protocol = split_protocols(read_rankings(f.parent))
        except (FileNotFoundError, ValueError, KeyError, TypeError, AttributeError) as exc:
            log.warning("%s: no per-query values (%s); its intervals are left out", f.parent, exc)
            continue
        for protocol, rankings in by_protocol.items():
            names = [n for n in recorded.get(protocol, {}) if n.partition("@")[0] in METRICS
                     and n.partition("@")[2].isdigit()]
            rk = sorted(int(n.partition("@")[2]) for n in names if n.startswith("recall@"))
            pk = sorted(int(n.partition("@")[2]) for n in names if n.startswith("precision@"))
            try:
                depth = int(rankings["rank"].max()) if len(rankings) else 0
                if any(k > depth for k in rk + pk):
                    log.warning("%s: the rankings hold the top %d: no interval for k > %d", f.parent, depth, depth)
                q = per_query_values(rankings, [k for k in rk if k <= depth], [k for k in pk if k <= depth])
            except (ValueError, KeyError) as exc:
                log.warning("%s (%s): no per-query values (%s); its intervals are left out", f.parent, protocol, exc)
                continue
            check_recorded_metrics(f.parent, protocol, recorded.get(protocol, {}), q)
            q.insert(0, "method", str(cell["method"]))
            q.insert(1, "scenario", str(cell["scenario"]))
            q.insert(2, "threshold", threshold_value(cell["threshold"]))
            q.insert(3, "seed", int(cell["seed"]))
            q.insert(4, "protocol", protocol)
            parts.append(q)
    if not parts:
        raise FileNotFoundError(f"{cells_root(study_name)}: no cell with a readable rankings.csv")
    df = pd.concat(parts, ignore_index=True)
    df = df[QUERY_KEYS + metric_cols(df)]
    return sort_rows(df, QUERY_KEYS)


def rankings_table(study_name: str, grid: Optional[Collection[str]] = None,
                   groups: Optional[Collection[tuple[str, str, float]]] = None, protocol: Optional[str] = None,
                   max_rank: Optional[int] = None) -> pd.DataFrame:
    """The ``rankings.csv`` rows of a study's cells with their keys: ``method, scenario, threshold, seed,
    protocol`` and `RANKING_COLUMNS`; with `groups` only the cells of those ``(method, scenario, threshold)``, with
    `protocol` only its rows, with `max_rank` only ranks up to it (``max_rank=1``: each query's top-1 match). A cell
    without readable rankings is left out with a warning (as in `query_table`). Empty (those columns) when nothing
    is left."""
    keep = None if groups is None else {(str(m), str(sc), threshold_value(t)) for m, sc, t in groups}
    parts = []
    for f in cell_files(study_name, grid):
        cell = io.read_json(f)
        try:
            base = (str(cell["method"]), str(cell["scenario"]), threshold_value(cell["threshold"]), int(cell["seed"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{f}: not a valid cell.json ({exc!r})") from exc
        if keep is not None and base[:3] not in keep:
            continue
        try:
            by_protocol = split_protocols(read_rankings(f.parent))
        except (FileNotFoundError, ValueError, KeyError) as exc:
            log.warning("%s: no rankings (%s); left out", f.parent, exc)
            continue
        for name, r in by_protocol.items():
            if protocol is not None and name != protocol:
                continue
            check_columns(r, RANKING_COLUMNS, f"{f.parent / 'rankings.csv'}")
            r = r[RANKING_COLUMNS]
            if max_rank is not None:
                r = r[r["rank"] <= max_rank]
            parts.append(r.assign(method=base[0], scenario=base[1], threshold=base[2], seed=base[3], protocol=name))
    keys = ["method", "scenario", "threshold", "seed", "protocol"]
    if not parts:
        return pd.DataFrame(columns=keys + RANKING_COLUMNS)
    return pd.concat(parts, ignore_index=True)[keys + RANKING_COLUMNS]


# ---- the paper's numbers ---------------------------------------------------------------------------------------

def paper_tables() -> pd.DataFrame:
    """The paper's Table 1 and Table 2 (``monolib/resources/paper_tables.csv``); thresholds as floats (inf)."""
    df = pd.read_csv(paths.RESOURCES / "paper_tables.csv")
    df["threshold"] = df["threshold"].astype(float)
    df["k"] = df["k"].astype(int)
    df["value"] = df["value"].astype(float)
    return df
