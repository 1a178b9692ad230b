"""The report stage: merge every cell of a study into Table 1, Table 2 and the figures.

Everything here reads files the cells wrote (``runs/<study>/cells/<method>/<scenario>__t<threshold>__s<seed>/``:
``cell.json``, ``rankings.csv``, ``protocol.csv``), never notebook outputs, and writes through the atomic helpers
of :mod:`monolib.io`, so a re-run on unchanged cells reproduces the same bytes.

Reference numbers
-----------------
``monolib/data/paper_tables.csv`` is a transcription of the paper's published Table 1 (recall@1/5/10) and
Table 2 (precision@2/4/6) from ``shared/docs/paper.md`` (columns ``scenario, threshold, metric, k, value, source``;
thresholds ``1, 2, 5, 10, inf``; values in percent). They are the paper's single-run numbers, not ours. Note that
the paper's own Table 1 is not monotone in k for Scenario 4 at 5 m (recall@5 87.5 > recall@10 86.3), which is
impossible for recall over one fixed ranking; it is transcribed as printed.

Uncertainty
-----------
Every number of the tables carries a 95 % interval from a hierarchical bootstrap over test settings, queries within
settings and seeds, computed from the cells' per-query rankings (`Bootstrap`, `intervals`; ``intervals.csv``), and
thresholds significantly below their scenario's best are marked by a paired bootstrap of the difference
(`threshold_tests`; ``threshold_tests.csv``). The same resample indices serve every cell of a study, so differences
between cells (thresholds, encoder variants in ``encoder_ablation``, depth scales) are paired.

Metric definitions (the design's protocol)
------------------------------------------
A query's candidates are its own setting's positives plus every frame of the protocol's other settings.
``recall@k``: share of queries with at least one frame of their own setting in the top k.
``precision@k``: mean over queries of (own-setting frames in the top k) / k. Values in percent.

Protocols
---------
A cell evaluates one trained encoder on two protocols (`monolib.retrieval.evaluate_protocols`): ``paper`` (test
settings of different families: the paper's protocol, the headline Tables 1-2) and ``siblings`` (pairs of settings
of one family, when the study has them: ``table1_recall_siblings.*``, ``table2_precision_siblings.*``). Every
per-query table (``results.csv``, ``intervals.csv``, ``threshold_tests.csv``, ...) has a ``protocol`` column, and
every statistic is computed within one protocol (its own bootstrap; nothing is paired across protocols). A cell
written before there were two protocols (flat ``metrics``, rankings without ``protocol``) reads as ``paper``.
"""
from __future__ import annotations

import logging
import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd

from monolib import io, paths
from monolib.params import PAPER, SIBLINGS  # the test protocols (monolib.params: no torch import here)
from monolib.params import PROTOCOLS as PROTOCOL_ORDER

log = logging.getLogger(__name__)

INF = math.inf
METRICS = ("recall", "precision")
RESULT_COLUMNS = ["method", "scenario", "threshold", "seed", "protocol", "metric", "k", "value"]
SUMMARY_KEYS = ["method", "scenario", "threshold", "protocol", "metric", "k"]
RANKING_COLUMNS = ["query", "query_setting", "rank", "match", "match_setting", "distance"]
PROTOCOL_COLUMNS = ["frame", "setting", "role"]
IMAGE_SCENARIO = "rgb"          # the scenario name image-only baselines are written under
TABLES = {"recall": ("table1_recall", "Table 1: Recall at k (%)"),
          "precision": ("table2_precision", "Table 2: Precision at k (%)")}

RgbOf = Callable[[str], Optional[np.ndarray]]


class ProtocolError(ValueError):
    """A cell's rankings break the evaluation protocol; the message names the query and the match."""


# ---- small helpers ---------------------------------------------------------------------------------------------

def _natural_key(text: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(text))]


def _threshold(value) -> float:
    """1 / 1.0 / '1' -> 1.0; 'inf' / 'Infinity' / inf -> inf."""
    return float(value) + 0.0


NO_EDGES = "0 (no edges)"


def threshold_label(t: float, tex: bool = False) -> str:
    """The threshold as the paper prints it: 1, 2, 5, 10, ∞ (``$\\infty$`` in TeX), 2.5; 0 (no edges: nodes
    only) as ``0 (no edges)``."""
    if t is None or (isinstance(t, float) and math.isnan(t)):
        return "–" if not tex else "--"
    if math.isinf(t):
        return r"$\infty$" if tex else "∞"
    if t == 0:
        return NO_EDGES
    return f"{t:g}"


def _method_order(methods) -> list[str]:
    from monolib.methods import METHODS

    registry = list(METHODS)
    return sorted(set(methods), key=lambda m: (registry.index(m) if m in registry else len(registry), m))


def _protocol_rank(name: str):
    return (PROTOCOL_ORDER.index(name), "") if name in PROTOCOL_ORDER else (len(PROTOCOL_ORDER), str(name))


def protocols_in(frame: pd.DataFrame) -> list[str]:
    """The protocols present in a frame with a ``protocol`` column, paper first."""
    return sorted(frame["protocol"].unique(), key=_protocol_rank) if "protocol" in frame.columns else [PAPER]


def only_protocol(frame: Optional[pd.DataFrame], protocol: str) -> Optional[pd.DataFrame]:
    """The rows of one protocol (a frame without a ``protocol`` column holds the paper protocol only)."""
    if frame is None:
        return None
    if "protocol" not in frame.columns:
        return frame if protocol == PAPER else frame.iloc[0:0]
    return frame[frame["protocol"] == protocol]


def split_protocols(rankings: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """``{protocol: its rows}`` of a cell's ``rankings.csv`` or ``protocol.csv`` (paper first); a file without a
    ``protocol`` column (a cell of one protocol) is ``{"paper": all rows}``."""
    if "protocol" not in rankings.columns:
        return {PAPER: rankings}
    return {p: rankings[rankings["protocol"] == p].reset_index(drop=True) for p in protocols_in(rankings)}


def _one_protocol_only(frame: pd.DataFrame, what: str) -> None:
    if "protocol" in frame.columns and frame["protocol"].nunique() > 1:
        raise ValueError(f"{what}: rows of protocols {protocols_in(frame)} together; select one (split_protocols)")


def cell_metrics(cell: Mapping) -> dict[str, dict[str, float]]:
    """``{protocol: {metric: value}}`` of a cell.json (flat ``metrics`` of an older cell: the paper protocol)."""
    m = cell["metrics"]
    if any(isinstance(v, Mapping) for v in m.values()):
        return {str(p): dict(v) for p, v in sorted(m.items(), key=lambda kv: _protocol_rank(kv[0]))}
    return {PAPER: dict(m)}


def _is_image(method: str, scenario: str) -> bool:
    from monolib.methods import METHODS

    if method in METHODS:
        return METHODS[method][0] == "image"
    return scenario == IMAGE_SCENARIO


def _cells_root(study_name: str) -> Path:
    return paths.study_dir(study_name) / "cells"


# ---- collect ---------------------------------------------------------------------------------------------------

def cell_files(study_name: str) -> list[Path]:
    """Every ``cell.json`` of a study, sorted."""
    return sorted(_cells_root(study_name).glob("*/*/cell.json"))


def collect(study_name: str) -> pd.DataFrame:
    """All cells of a study in long format: one row per number.

    Columns ``method, scenario, threshold (float, inf for 'inf'), seed, protocol ('paper'|'siblings'), metric
    ('recall'|'precision'), k, value`` (percent), sorted by method, scenario (natural order), threshold, seed,
    protocol, metric, k. Raises FileNotFoundError when the study has no cell yet.
    """
    files = cell_files(study_name)
    if not files:
        raise FileNotFoundError(f"{_cells_root(study_name)}: no cell.json found; run the study's cells first")
    rows = []
    for f in files:
        cell = io.read_json(f)
        try:
            base = (str(cell["method"]), str(cell["scenario"]), _threshold(cell["threshold"]), int(cell["seed"]))
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
    return _sort(df, ["method", "scenario", "threshold", "seed", "protocol", "metric", "k"])


def _sort(df: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    def key(col: pd.Series):
        if col.name == "scenario":
            return col.map(lambda s: tuple((0, x, "") if isinstance(x, int) else (1, 0, x) for x in _natural_key(s)))
        if col.name == "method":
            order = _method_order(col.unique())
            return col.map(order.index)
        if col.name == "protocol":
            return col.map(_protocol_rank)
        return col

    return df.sort_values(by, key=key, kind="mergesort").reset_index(drop=True)


def recorded_labels(study_name: str) -> dict[str, str]:
    """``{scenario: label}`` as the cells recorded them (``scenario_label`` in cell.json)."""
    out: dict[str, str] = {}
    for f in cell_files(study_name):
        cell = io.read_json(f)
        if cell.get("scenario_label"):
            out.setdefault(str(cell["scenario"]), str(cell["scenario_label"]))
    return dict(sorted(out.items(), key=lambda kv: _natural_key(kv[0])))


def labels_of(study) -> dict[str, str]:
    """``{scenario: label}`` from a loaded study (`monolib.params.Study`)."""
    return {name: (sc.label or name) for name, sc in study.scenarios.items()}


class RgbReader:
    """``rgb_of(frame_key) -> uint8 (H, W, 3)`` on a study's dataset, opened at the first call.

    A frame (or a dataset) that cannot be read gives None and one warning, so Figure 5 shows a grey placeholder
    instead of losing the whole report.
    """

    def __init__(self, study):
        self.study = study
        self._ds = None
        self._failed: Optional[str] = None

    def __call__(self, key: str) -> Optional[np.ndarray]:
        from monolib import dataset
        from monolib.io import DataFileError

        if self._failed is not None:
            return None
        try:
            if self._ds is None:
                self._ds = dataset.open_dataset(self.study)
            return self._ds.frame_by_key(key).rgb
        except (DataFileError, OSError, ValueError) as exc:
            if self._ds is None:
                self._failed = str(exc)
            log.warning("figure 5: no image for %s (%s)", key, exc)
            return None


def rgb_reader(study) -> RgbOf:
    """``rgb_of(frame_key) -> uint8 (H, W, 3)`` on the study's dataset (a `Study` or a study name); see `RgbReader`."""
    from monolib import params

    if isinstance(study, (str, Path)):
        study = params.load_study(study)
    return RgbReader(study)


# ---- recomputing the metrics -----------------------------------------------------------------------------------

def _check_columns(df: pd.DataFrame, columns: list[str], what: str) -> None:
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{what}: missing columns {missing} (have {list(df.columns)})")


def hit_matrix(rankings: pd.DataFrame) -> tuple[pd.Index, np.ndarray]:
    """(queries, hits): ``hits[i, r]`` is True when query i's rank r+1 candidate is from the query's setting.
    The rankings of one protocol (`split_protocols`)."""
    _check_columns(rankings, RANKING_COLUMNS, "rankings")
    _one_protocol_only(rankings, "rankings")
    codes, queries = pd.factorize(rankings["query"], sort=True)
    ranks = rankings["rank"].to_numpy(dtype=int)
    if len(ranks) and ranks.min() < 1:
        raise ValueError("rankings: ranks start at 1")
    depth = int(ranks.max()) if len(ranks) else 0
    hits = np.zeros((len(queries), depth), dtype=bool)
    hits[codes, ranks - 1] = (rankings["match_setting"].to_numpy() == rankings["query_setting"].to_numpy())
    return queries, hits


def recompute_metrics(rankings: pd.DataFrame, recall_k, precision_k,
                      positives_per_setting: int | Mapping[str, int] | pd.Series | None = None) -> dict[str, float]:
    """recall@k and precision@k (percent) recomputed from a cell's ``rankings.csv``, vectorised.

    ``positives_per_setting`` None (default, the paper's definition): precision@k divides by k. Given (one number,
    or a mapping setting -> number of positives), it divides by ``min(k, positives of the query's setting)``, the
    best reachable share when a setting has fewer positives than k. Raises ValueError when a k exceeds the
    depth of the rankings (the cells store the top 10).
    """
    queries, hits = hit_matrix(rankings)
    ks = [int(k) for k in recall_k] + [int(k) for k in precision_k]
    if ks and max(ks) > hits.shape[1]:
        raise ValueError(f"rankings: k={max(ks)} needs the top {max(ks)}, the rankings hold the top {hits.shape[1]}")
    if len(queries) == 0:
        raise ValueError("rankings: no query")
    found = np.cumsum(hits, axis=1)     # own-setting frames within the top r+1
    out: dict[str, float] = {}
    for k in recall_k:
        out[f"recall@{int(k)}"] = float(100.0 * np.mean(found[:, int(k) - 1] > 0))
    if positives_per_setting is not None:
        setting_of = rankings.drop_duplicates("query").set_index("query")["query_setting"].reindex(queries)
        if isinstance(positives_per_setting, (int, np.integer, float)):
            npos = np.full(len(queries), float(positives_per_setting))
        else:
            npos = setting_of.map(pd.Series(positives_per_setting)).to_numpy(dtype=float)
            if np.isnan(npos).any():
                raise ValueError(f"positives_per_setting: no count for settings "
                                 f"{sorted(set(setting_of[np.isnan(npos)]))}")
    for k in precision_k:
        k = int(k)
        den = np.minimum(k, npos) if positives_per_setting is not None else float(k)
        out[f"precision@{k}"] = float(100.0 * np.mean(found[:, k - 1] / den))
    return out


def check_protocol(rankings: pd.DataFrame, protocol: pd.DataFrame, positives: Optional[int] = None) -> dict:
    """Raise `ProtocolError` when a cell's rankings break the protocol drawn in its ``protocol.csv``.

    Checked: every ranked query is a protocol query of the setting it claims; settings agree with frame keys;
    (query, rank) and (query, match) are unique; no query retrieves itself; a candidate of the query's own setting
    is one of that setting's positives (never another query, nor a frame outside the draw); every candidate is of
    one of the protocol's settings; no setting has more than ``positives`` positives (when given). One
    protocol's rows (`split_protocols`; `check_protocols` checks every protocol of a cell). Returns counts
    ``{"queries", "settings", "positives"}``.
    """
    _check_columns(rankings, RANKING_COLUMNS, "rankings")
    _check_columns(protocol, PROTOCOL_COLUMNS, "protocol")
    _one_protocol_only(rankings, "rankings")
    _one_protocol_only(protocol, "protocol")
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
    fail(rankings["query"].map(setting_of) != rankings["query_setting"], "rankings: query_setting disagrees with the protocol")
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
                    settings: Optional[Mapping[str, int]] = None) -> dict[str, dict]:
    """`check_protocol` for every protocol of a cell (``rankings.csv`` and ``protocol.csv`` with their
    ``protocol`` column), and the protocols' shapes: ``paper``'s settings are all of different families
    (``ai_VVV``), ``siblings``' settings are pairs of one family; with `settings` (``{protocol: number of
    settings}``) each protocol has that many. Both files must hold the same protocols.
    Returns ``{protocol: counts}``."""
    from monolib.retrieval import family

    ranked, drawn = split_protocols(rankings), split_protocols(protocol)
    if list(ranked) != list(drawn):
        raise ProtocolError(f"rankings hold protocols {list(ranked)}, protocol.csv {list(drawn)}")
    out = {}
    for name, r in ranked.items():
        d = drawn[name]
        out[name] = check_protocol(r, d, positives)
        names = sorted(d["setting"].astype(str).unique())
        fams = pd.Series(names).map(family).value_counts()
        if name == PAPER and (fams > 1).any():
            raise ProtocolError(f"protocol {name}: settings of one family: {sorted(n for n in names if fams[family(n)] > 1)}")
        if name == SIBLINGS and (fams != 2).any():
            raise ProtocolError(f"protocol {name}: families without exactly 2 settings: {sorted(fams[fams != 2].index)}")
        if settings is not None and name in settings and len(names) != settings[name]:
            raise ProtocolError(f"protocol {name}: {len(names)} settings, {settings[name]} expected")
    if settings is not None and set(settings) != set(out):
        raise ProtocolError(f"protocols {list(out)}, expected {list(settings)}")
    return out


# ---- summary and the paper's numbers ---------------------------------------------------------------------------

def summary(results: pd.DataFrame) -> pd.DataFrame:
    """Mean, sample std (ddof 1; NaN when n = 1) and n over seeds per (method, scenario, threshold, protocol,
    metric, k)."""
    keys = [k for k in SUMMARY_KEYS if k in results.columns]
    g = results.groupby(keys, sort=False)["value"]
    out = g.agg(mean="mean", std="std", n="count").reset_index()
    return _sort(out, keys)


def paper_tables() -> pd.DataFrame:
    """The paper's Table 1 and Table 2 (``monolib/data/paper_tables.csv``); thresholds as floats (inf)."""
    df = pd.read_csv(paths.DATA / "paper_tables.csv")
    df["threshold"] = df["threshold"].astype(float)
    df["k"] = df["k"].astype(int)
    df["value"] = df["value"].astype(float)
    return df


# ---- uncertainty: bootstrap over test settings, queries and seeds ---------------------------------------------
#
# Every number of the tables is a mean over seeds of a mean over the queries of the test settings. Its 95 %
# interval comes from a hierarchical bootstrap over the three sources of variation: per resample, the seeds are
# drawn with replacement, the settings are drawn with replacement, and within each drawn (seed, setting) its
# queries are drawn with replacement; the statistic is the mean of the drawn per-query values (recall@k: a hit
# indicator x 100; precision@k: the own-setting share of the top k x 100). The interval is the 2.5 and 97.5
# percentiles over B resamples.
#
# The resample *indices* are one fixed set per study (`Bootstrap`, numpy seed 0): uniform numbers drawn once for
# [B, seed slot], [B, setting slot] and [B, seed slot, setting slot, query slot], turned into indices by
# floor(u * n). Every cell group of a study is resampled with the same numbers, and since the protocol draw
# depends only on the seed (same queries in every method, scenario and threshold of a seed), two groups resampled
# with the same numbers are paired: the difference of their resampled means is the paired bootstrap of the
# difference (`paired_difference` joins the per-query values on seed, setting and query first, so a group against
# itself gives exactly 0).

N_BOOT = 1000
BOOT_SEED = 0
QUERY_KEYS = ["method", "scenario", "threshold", "seed", "protocol", "setting", "query"]
GROUP_KEYS = ["method", "scenario", "threshold", "protocol"]
INTERVAL_COLUMNS = ["method", "scenario", "threshold", "protocol", "metric", "k", "mean", "ci_lo", "ci_hi", "n_seeds"]
DAGGER = "†"
STAR = "*"


def metric_columns(recall_k, precision_k) -> list[str]:
    return [f"recall@{int(k)}" for k in recall_k] + [f"precision@{int(k)}" for k in precision_k]


def _split_metric(col: str) -> tuple[str, int]:
    metric, _, k = col.partition("@")
    return metric, int(k)


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


def _metric_cols(frame: pd.DataFrame) -> list[str]:
    cols = [c for c in frame.columns if "@" in str(c)]
    return sorted(cols, key=lambda c: (METRICS.index(_split_metric(c)[0]), _split_metric(c)[1]))


def query_table(study_name: str) -> pd.DataFrame:
    """Per-query values of every cell of a study: ``method, scenario, threshold, seed, protocol, setting, query``
    and one column per metric the cell recorded (see `per_query_values`), read from each cell's ``rankings.csv``,
    protocol by protocol."""
    parts = []
    for f in cell_files(study_name):
        cell = io.read_json(f)
        try:
            recorded = cell_metrics(cell)
            by_protocol = split_protocols(_read_rankings(f.parent))
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
            q.insert(0, "method", str(cell["method"]))
            q.insert(1, "scenario", str(cell["scenario"]))
            q.insert(2, "threshold", _threshold(cell["threshold"]))
            q.insert(3, "seed", int(cell["seed"]))
            q.insert(4, "protocol", protocol)
            parts.append(q)
    if not parts:
        raise FileNotFoundError(f"{_cells_root(study_name)}: no cell with a readable rankings.csv")
    df = pd.concat(parts, ignore_index=True)
    df = df[QUERY_KEYS + _metric_cols(df)]
    return _sort(df, QUERY_KEYS)


class Bootstrap:
    """The fixed resample of one study: ``n_boot`` draws of seeds, settings and queries (numpy seed `seed`).

    Sized for at most `n_seeds` seeds, `n_settings` settings and `n_queries` queries per (seed, setting); a group
    with fewer uses the first slots, so groups of the same shape are resampled with identical indices.
    """

    def __init__(self, n_seeds: int, n_settings: int, n_queries: int, n_boot: int = N_BOOT, seed: int = BOOT_SEED,
                 chunk_elements: int = 2_000_000):
        rng = np.random.default_rng(seed)
        self.n_boot, self.shape = int(n_boot), (int(n_seeds), int(n_settings), int(n_queries))
        self.u_seed = rng.random((self.n_boot, self.shape[0]))
        self.u_setting = rng.random((self.n_boot, self.shape[1]))
        self.u_query = rng.random((self.n_boot, *self.shape))
        self.chunk_elements = int(chunk_elements)

    @classmethod
    def for_queries(cls, qv: pd.DataFrame, n_boot: int = N_BOOT, seed: int = BOOT_SEED) -> "Bootstrap":
        """Sized for every group of a `query_table`."""
        if qv.empty:
            return cls(1, 1, 1, n_boot, seed)
        if "protocol" not in qv.columns:
            qv = qv.assign(protocol=PAPER)
        n_seeds = int(qv.groupby(GROUP_KEYS)["seed"].nunique().max())
        n_settings = int(qv.groupby(GROUP_KEYS + ["seed"])["setting"].nunique().max())
        n_settings = max(n_settings, int(qv["setting"].nunique()))
        n_queries = int(qv.groupby(GROUP_KEYS + ["seed", "setting"]).size().max())
        return cls(n_seeds, n_settings, n_queries, n_boot, seed)

    @staticmethod
    def cube(frame: pd.DataFrame, cols: list[str], settings: Optional[list] = None) -> tuple[np.ndarray, np.ndarray]:
        """(values [seed, setting, query slot, metric], counts [seed, setting]) of one group's per-query rows
        (columns ``seed, setting, query`` and `cols`); seeds, settings and queries in sorted order."""
        frame = frame.sort_values(["seed", "setting", "query"], kind="mergesort")
        seeds = np.sort(frame["seed"].unique())
        settings = sorted(frame["setting"].unique()) if settings is None else list(settings)
        ri = np.searchsorted(seeds, frame["seed"].to_numpy())
        si = pd.Index(settings).get_indexer(frame["setting"])
        if (si < 0).any():
            raise ValueError("cube: a row's setting is not in the given settings")
        slot = frame.groupby(["seed", "setting"], sort=False).cumcount().to_numpy()
        nq = np.zeros((len(seeds), len(settings)), dtype=np.intp)
        np.add.at(nq, (ri, si), 1)
        values = np.zeros((len(seeds), len(settings), int(nq.max()) if nq.size else 0, len(cols)))
        values[ri, si, slot] = frame[cols].to_numpy(dtype=float)
        return values, nq

    def check(self, values: np.ndarray, offset: int = 0) -> None:
        r, s, q = values.shape[:3]
        if r > self.shape[0] or offset + s > self.shape[1] or q > self.shape[2]:
            raise ValueError(f"bootstrap sized {self.shape} cannot resample a group of shape {(r, s, q)} "
                             f"(setting offset {offset})")

    @staticmethod
    def observed(values: np.ndarray, nq: np.ndarray) -> np.ndarray:
        """The mean per metric of every (seed, setting, query) value: the point estimate."""
        valid = np.arange(values.shape[2]) < nq[..., None]
        return np.einsum("rsqm,rsq->m", values, valid.astype(float)) / max(int(valid.sum()), 1)

    def resample(self, values: np.ndarray, nq: np.ndarray, offset: int = 0) -> np.ndarray:
        """[B, metric] resampled means (seeds, settings, then queries within each drawn (seed, setting), all with
        replacement). `offset` shifts the setting slots used (independent draws for a second set of settings)."""
        self.check(values, offset)
        r, s, q, m = values.shape
        out = np.empty((self.n_boot, m))
        step = max(1, self.chunk_elements // max(1, r * s * max(q, 1) * m))
        slots = np.arange(q)
        for b0 in range(0, self.n_boot, step):
            b1 = min(self.n_boot, b0 + step)
            rs = np.minimum((self.u_seed[b0:b1, :r] * r).astype(np.intp), r - 1)                       # [b, R]
            gs = np.minimum((self.u_setting[b0:b1, offset:offset + s] * s).astype(np.intp), s - 1)      # [b, S]
            n = nq[rs[:, :, None], gs[:, None, :]]                                                     # [b, R, S]
            qi = (self.u_query[b0:b1, :r, offset:offset + s, :q] * n[..., None]).astype(np.intp)       # [b, R, S, Q]
            qi = np.clip(qi, 0, np.maximum(n[..., None] - 1, 0))
            valid = (slots < n[..., None]).astype(float)
            drawn = values[rs[:, :, None, None], gs[:, None, :, None], qi]                            # [b, R, S, Q, M]
            with np.errstate(invalid="ignore", divide="ignore"):
                out[b0:b1] = np.einsum("brsqm,brsq->bm", drawn, valid) / valid.sum(axis=(1, 2, 3))[:, None]
        return out

    def interval(self, values: np.ndarray, nq: np.ndarray, offset: int = 0) -> dict[str, np.ndarray]:
        """``{"mean", "ci_lo", "ci_hi", "boot"}`` per metric (percentiles 2.5 and 97.5 of the resampled means)."""
        boot = self.resample(values, nq, offset)
        lo, hi = np.nanpercentile(boot, [2.5, 97.5], axis=0)
        return {"mean": self.observed(values, nq), "ci_lo": lo, "ci_hi": hi, "boot": boot}


def _rows_of(qv: pd.DataFrame, method: str, scenario: str, threshold: float,
             protocol: Optional[str] = None) -> pd.DataFrame:
    rows = qv[(qv["method"] == method) & (qv["scenario"] == scenario) & (qv["threshold"] == threshold)]
    return rows if protocol is None else only_protocol(rows, protocol)


def _group_cols(frame: pd.DataFrame, cols: Optional[list[str]] = None) -> list[str]:
    cols = _metric_cols(frame) if cols is None else cols
    return [c for c in cols if c in frame.columns and frame[c].notna().all()]


def intervals(qv: pd.DataFrame, boot: Bootstrap) -> pd.DataFrame:
    """``intervals.csv``: per (method, scenario, threshold, protocol, metric, k) the mean and its 95 % bootstrap
    interval, and the number of seeds (columns `INTERVAL_COLUMNS`). Pass one protocol's rows with its own
    `Bootstrap` (as `write_report` does) for intervals independent of the other protocol."""
    rows = []
    if "protocol" not in qv.columns:
        qv = qv.assign(protocol=PAPER)
    for (method, scenario, threshold, protocol), g in qv.groupby(GROUP_KEYS, sort=False):
        cols = _group_cols(g)
        if not cols:
            continue
        values, nq = boot.cube(g, cols)
        iv = boot.interval(values, nq)
        for j, c in enumerate(cols):
            metric, k = _split_metric(c)
            rows.append((method, scenario, float(threshold), protocol, metric, k, float(iv["mean"][j]),
                         float(iv["ci_lo"][j]), float(iv["ci_hi"][j]), int(g["seed"].nunique())))
    out = pd.DataFrame(rows, columns=INTERVAL_COLUMNS)
    return _sort(out, SUMMARY_KEYS)


def paired_difference(a: pd.DataFrame, b: pd.DataFrame, boot: Bootstrap,
                      cols: Optional[list[str]] = None) -> pd.DataFrame:
    """Paired bootstrap of mean(a) - mean(b) over the (seed, setting, query) triples the two share.

    `a` and `b` are per-query rows (``seed, setting, query`` + metric columns), e.g. two cells groups of one
    study. Returns one row per metric column: ``metric, k, diff, ci_lo, ci_hi, significant`` (the interval
    excludes 0), and ``n_seeds``, ``n_queries`` of the shared rows.
    """
    cols = [c for c in (_group_cols(a, cols)) if c in _group_cols(b, cols)]
    keys = ["seed", "setting", "query"] + (["protocol"] if "protocol" in a.columns and "protocol" in b.columns else [])
    j = a[keys + cols].merge(b[keys + cols], on=keys, how="inner", suffixes=("_a", "_b"), validate="one_to_one")
    d = j[keys].drop(columns="protocol", errors="ignore").copy()
    for c in cols:
        d[c] = j[f"{c}_a"].to_numpy(dtype=float) - j[f"{c}_b"].to_numpy(dtype=float)
    rows = []
    if len(d) and cols:
        values, nq = boot.cube(d, cols)
        iv = boot.interval(values, nq)
        for i, c in enumerate(cols):
            lo, hi = float(iv["ci_lo"][i]), float(iv["ci_hi"][i])
            rows.append((*_split_metric(c), float(iv["mean"][i]), lo, hi, bool(lo > 0 or hi < 0),
                         int(d["seed"].nunique()), len(d)))
    return pd.DataFrame(rows, columns=["metric", "k", "diff", "ci_lo", "ci_hi", "significant", "n_seeds", "n_queries"])


def _best_threshold(means: pd.Series) -> float:
    """The threshold with the highest mean (index: thresholds); ties (to 1e-9): the smallest threshold."""
    top = means.max()
    return float(min(t for t, v in means.items() if v >= top - 1e-9))


TEST_COLUMNS = ["method", "scenario", "protocol", "metric", "k", "threshold", "best_threshold", "diff", "ci_lo",
                "ci_hi", "significant"]


def threshold_tests(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap) -> pd.DataFrame:
    """Per (method, scenario, protocol, metric, k) with more than one threshold: every threshold against the
    scenario's best (highest mean; ties: the smallest threshold), paired bootstrap of (threshold - best) on the
    protocol's queries. Columns `TEST_COLUMNS` (significant: the interval excludes 0, i.e. significantly worse
    than the best)."""
    rows = []
    if "protocol" not in iv.columns:
        iv = iv.assign(protocol=PAPER)
    for (method, scenario, protocol), g in iv.groupby(["method", "scenario", "protocol"], sort=False):
        if g["threshold"].nunique() < 2:
            continue
        best = {f"{m}@{k}": _best_threshold(gm.set_index("threshold")["mean"])
                for (m, k), gm in g.groupby(["metric", "k"], sort=False)}
        for t in sorted(g["threshold"].unique()):
            for b in sorted(set(best.values()) - {t}):
                cols = [c for c, bt in best.items() if bt == b]
                d = paired_difference(_rows_of(qv, method, scenario, t, protocol),
                                      _rows_of(qv, method, scenario, b, protocol), boot, cols)
                for r in d.itertuples(index=False):
                    rows.append((method, scenario, protocol, r.metric, int(r.k), float(t), b, r.diff, r.ci_lo,
                                 r.ci_hi, bool(r.significant)))
    out = pd.DataFrame(rows, columns=TEST_COLUMNS)
    out["metric_order"] = out["metric"].map(METRICS.index)
    out = _sort(out, ["method", "scenario", "protocol", "metric_order", "k", "threshold"]).drop(columns="metric_order")
    return out


# ---- tables ----------------------------------------------------------------------------------------------------

def _table_frame(results: pd.DataFrame, metric: str, iv: Optional[pd.DataFrame] = None,
                 tests: Optional[pd.DataFrame] = None) -> pd.DataFrame:
    """The machine-readable table of one protocol's rows: method, scenario, threshold, protocol, k, mean, std, n,
    [ci_lo, ci_hi,] paper, [worse_than_best] (+ layout helpers). The paper's numbers sit beside the ``paper``
    protocol only (the paper never ran the siblings protocol)."""
    if "protocol" not in results.columns:
        results = results.assign(protocol=PAPER)
    _one_protocol_only(results, "table")
    on = ["method", "scenario", "threshold", "protocol", "k"]
    s = summary(results[results["metric"] == metric])
    if iv is not None:
        iv = iv if "protocol" in iv.columns else iv.assign(protocol=PAPER)
        ci = iv[iv["metric"] == metric][SUMMARY_KEYS + ["ci_lo", "ci_hi"]].drop(columns="metric")
        s = s.merge(ci, on=on, how="left")
    paper = paper_tables()
    paper = paper[paper["metric"] == metric][["scenario", "threshold", "k", "value"]].rename(columns={"value": "paper"})
    paper["method"] = "gcn"     # the paper's numbers are its GCN's, on its protocol
    paper["protocol"] = PAPER
    s = s.merge(paper, on=on, how="left")
    if tests is not None:
        tests = tests if "protocol" in tests.columns else tests.assign(protocol=PAPER)
        tt = tests[tests["metric"] == metric][on + ["significant"]]
        s = s.merge(tt.rename(columns={"significant": "worse_than_best"}), on=on, how="left")
        s["worse_than_best"] = s["worse_than_best"].astype("boolean").fillna(False).astype(bool)
    s["image"] = [_is_image(m, sc) for m, sc in zip(s["method"], s["scenario"])]
    # graph methods first, by scenario (each variant right below the paper's gcn), image baselines below
    s["_img"] = s["image"].astype(int)
    s = _sort(s, ["_img", "scenario", "method", "threshold", "k"]).drop(columns="_img")
    return s


def _fmt(mean: float, std: float, n: int) -> str:
    if mean is None or not np.isfinite(mean):
        return "–"
    if n > 1 and np.isfinite(std):
        return f"{mean:.1f} ± {std:.1f}"
    return f"{mean:.1f}"


def _fmt_ci(lo, hi) -> str:
    if lo is None or hi is None or not (np.isfinite(lo) and np.isfinite(hi)):
        return ""
    return f"[{lo:.1f}, {hi:.1f}]"


def _layout(results: pd.DataFrame, metric: str, scenario_labels: Mapping[str, str],
            iv: Optional[pd.DataFrame] = None, tests: Optional[pd.DataFrame] = None):
    """Rows of the paper's layout: one per (method, scenario, threshold), cells per k, best marked.

    A cell is ``{"mean", "std", "n", "best", "ci" (text, '' without intervals), "worse" (dagger)}``."""
    t = _table_frame(results, metric, iv, tests)
    ks = sorted(t["k"].unique())
    t["shown"] = t["mean"].round(1)
    best = t.groupby(["method", "scenario", "k"])["shown"].transform("max")
    size = t.groupby(["method", "scenario", "k"])["shown"].transform("size")
    t["best"] = (t["shown"] == best) & (size > 1)
    rows = []
    for (method, scenario, threshold), g in t.groupby(["method", "scenario", "threshold"], sort=False):
        g = g.set_index("k")
        image = bool(g["image"].iloc[0])
        label = "RGB only" if image else f"{scenario}: {scenario_labels.get(scenario, scenario)}"
        cells = {}
        for k in ks:
            if k not in g.index:
                cells[k] = None
                continue
            r = g.loc[k]
            cells[k] = {"mean": r["mean"], "std": r["std"], "n": int(r["n"]), "best": bool(r["best"]),
                        "ci": _fmt_ci(r["ci_lo"], r["ci_hi"]) if "ci_lo" in g.columns else "",
                        "worse": bool(r["worse_than_best"]) if "worse_than_best" in g.columns else False}
        rows.append({
            "method": method, "scenario": scenario, "label": label, "image": image,
            "threshold": None if image else threshold, "cells": cells,
            "paper": {k: (g.loc[k, "paper"] if k in g.index else np.nan) for k in ks},
        })
    return t, ks, rows


def _n_note(t: pd.DataFrame) -> str:
    ns = sorted(t["n"].unique())
    if len(ns) == 1:
        n = int(ns[0])
        return f"n = {n} seed{'s' if n != 1 else ''}" + ("" if n > 1 else " (mean only)")
    return f"n = {int(ns[0])}–{int(ns[-1])} seeds (see the csv)"


PROTOCOL_NOTES = {
    PAPER: "Protocol `paper` (the paper's): each test setting is of another family (ai_VVV); a query's candidates "
           "are its setting's positives and every frame of the other settings.",
    SIBLINGS: "Protocol `siblings` (the paper's \"two neighbouring offices\", which it never tested): pairs of test "
              "settings of one family (same furniture and materials, another layout); a query's candidates are its "
              "setting's positives and every frame of the other settings, its sibling's included. Same trained "
              "encoders as the `paper` tables.",
}


def _protocol_of(t: pd.DataFrame) -> str:
    return str(t["protocol"].iloc[0]) if "protocol" in t.columns and len(t) else PAPER


def _caption(metric: str, t: pd.DataFrame, tex: bool = False, n_boot: Optional[int] = None) -> str:
    pm, inf, dag = (r"$\pm$", r"$\infty$", r"$^\dagger$") if tex else ("±", "∞", DAGGER)
    ours = "Ours: one seed" if set(t["n"]) == {1} else f"Ours: mean {pm} std over seeds, {_n_note(t)}"
    protocol = _protocol_of(t)
    note = PROTOCOL_NOTES.get(protocol, f"Protocol `{protocol}`.")
    note = note.replace("`", "").replace("_", r"\_") if tex else note
    if t["paper"].notna().any():
        text = (f"{note} {ours}; paper: the published single-run number "
                f"(GCN rows, thresholds 1, 2, 5, 10, {inf}). ")
    else:
        text = f"{note} {ours}. "
    text += "Bold: best mean per method and scenario for each k."
    if (t["threshold"] == 0).any():
        text += " Threshold 0: no edges (the encoder sees the nodes only)."
    if "ci_lo" in t.columns:
        text += (f" [lo, hi]: 95% bootstrap interval of our mean ({n_boot or N_BOOT} resamples of test settings, "
                 f"of queries within each setting and of seeds, all with replacement).")
    if "worse_than_best" in t.columns:
        text += (f" {dag}: significantly below the best threshold of its method and scenario for this k (paired "
                 f"bootstrap of the difference on the same queries, 95% interval excluding 0; each threshold "
                 f"tested on its own, no correction for multiple comparisons).")
    return text.replace("%", r"\%") if tex else text


def _cell_text(c: Optional[dict], tex: bool) -> str:
    if c is None:
        return "--" if tex else "–"
    main = _fmt(c["mean"], c["std"], c["n"])
    if tex:
        main = _tex(main)
        text = rf"\textbf{{{main}}}" if c["best"] else main
        if c["ci"]:
            text += rf" {{\scriptsize {c['ci']}}}"
        return text + (r"$^\dagger$" if c["worse"] else "")
    text = f"**{main}**" if c["best"] else main
    if c["ci"]:
        text += f" {c['ci']}"
    return text + (DAGGER if c["worse"] else "")


def _title(metric: str, t: pd.DataFrame) -> str:
    protocol = _protocol_of(t)
    return TABLES[metric][1] + ("" if protocol == PAPER else f", {protocol} protocol")


def _md_table(metric: str, results, scenario_labels, iv=None, tests=None, n_boot=None) -> str:
    t, ks, rows = _layout(results, metric, scenario_labels, iv, tests)
    title = _title(metric, t)
    has_paper = t["paper"].notna().any()
    head = ["method", "data", "threshold (m)"] + [f"k={k}" for k in ks]
    if has_paper:
        head += [f"paper k={k}" for k in ks]
    lines = [f"**{title}.** {_caption(metric, t, n_boot=n_boot)}", "",
             "| " + " | ".join(head) + " |",
             "|" + "|".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + "|"]
    prev = None
    for r in rows:
        group = (r["method"], r["scenario"])
        first = group != prev
        prev = group
        cells = [_cell_text(r["cells"][k], tex=False) for k in ks]
        line = [r["method"] if first else "", r["label"] if first else "", threshold_label(r["threshold"])] + cells
        if has_paper:
            line += [f"{r['paper'][k]:.1f}" if np.isfinite(r["paper"][k]) else "" for k in ks]
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines) + "\n"


_TEX_ESCAPE = {"&": r"\&", "%": r"\%", "_": r"\_", "#": r"\#", "$": r"\$", "{": r"\{", "}": r"\}", "~": r"\~{}",
               "^": r"\^{}", "±": r"$\pm$", "∞": r"$\infty$", "–": "--", "†": r"$^\dagger$", "Δ": r"$\Delta$"}


def _tex(text: str) -> str:
    return "".join(_TEX_ESCAPE.get(ch, ch) for ch in str(text))


def _tex_table(metric: str, results, scenario_labels, iv=None, tests=None, n_boot=None) -> str:
    t, ks, rows = _layout(results, metric, scenario_labels, iv, tests)
    name, title = TABLES[metric][0] + _suffix(_protocol_of(t)), _title(metric, t)
    has_paper = t["paper"].notna().any()
    nk = len(ks)
    cols = "lll" + "r" * nk + ("r" * nk if has_paper else "")
    out = [r"\begin{table}[t]", r"\centering", r"\small",
           rf"\caption{{\textbf{{{_tex(title)}.}} {_caption(metric, t, tex=True, n_boot=n_boot)}}}",
           rf"\label{{tab:{name}}}", rf"\begin{{tabular}}{{{cols}}}", r"\toprule"]
    group = rf" & & & \multicolumn{{{nk}}}{{c}}{{ours, $k$}}"
    rule = rf"\cmidrule(lr){{4-{3 + nk}}}"
    if has_paper:
        group += rf" & \multicolumn{{{nk}}}{{c}}{{paper, $k$}}"
        rule += rf"\cmidrule(lr){{{4 + nk}-{3 + 2 * nk}}}"
    out += [group + r" \\", rule]
    out.append("Method & Data & Threshold (m) & " + " & ".join(str(k) for k in ks * (2 if has_paper else 1)) + r" \\")
    out.append(r"\midrule")
    prev = None
    for r in rows:
        group_key = (r["method"], r["scenario"])
        first = group_key != prev
        if first and prev is not None:
            out.append(r"\midrule")
        prev = group_key
        cells = [_cell_text(r["cells"][k], tex=True) for k in ks]
        line = [_tex(r["method"]) if first else "", _tex(r["label"]) if first else "",
                threshold_label(r["threshold"], tex=True)] + cells
        if has_paper:
            line += [f"{r['paper'][k]:.1f}" if np.isfinite(r["paper"][k]) else "" for k in ks]
        out.append(" & ".join(line) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out) + "\n"


def _csv_table(metric: str, results, iv=None, tests=None) -> str:
    t = _table_frame(results, metric, iv, tests)
    cols = ["method", "scenario", "threshold", "k", "mean", "std", "n"]
    cols += ["ci_lo", "ci_hi"] if iv is not None else []
    cols += ["paper"] + (["worse_than_best"] if tests is not None else [])
    t = t[cols].copy()
    t["threshold"] = t["threshold"].map(paths.threshold_tag)
    for c in ("mean", "std", "paper", "ci_lo", "ci_hi"):
        if c in t.columns:
            t[c] = t[c].round(4)
    return t.to_csv(index=False, lineterminator="\n")


def table_markdown(results: pd.DataFrame, metric: str, scenario_labels: Optional[Mapping[str, str]] = None,
                   intervals: Optional[pd.DataFrame] = None, tests: Optional[pd.DataFrame] = None) -> str:
    """Table 1 (``metric='recall'``) or Table 2 (``'precision'``) as markdown."""
    return _md_table(metric, results, scenario_labels or {}, intervals, tests)


def _suffix(protocol: str) -> str:
    """File-name suffix of a protocol's tables: '' for the paper protocol (the headline tables), else '_<name>'."""
    return "" if protocol == PAPER else f"_{protocol}"


def write_tables(results: pd.DataFrame, out_dir: str | Path,
                 scenario_labels: Optional[Mapping[str, str]] = None, intervals: Optional[pd.DataFrame] = None,
                 tests: Optional[pd.DataFrame] = None, n_boot: Optional[int] = None,
                 protocol: str = PAPER) -> dict[str, Path]:
    """Write ``table1_recall.{md,csv,tex}`` and ``table2_precision.{md,csv,tex}`` of one protocol into `out_dir`
    (the ``paper`` protocol; another protocol's files end in ``_<protocol>``: ``table1_recall_siblings.md``, keys
    ``table1_siblings_md``...). `results`, `intervals` and `tests` may hold every protocol: the rows of `protocol`
    are used.

    Rows: method / scenario x threshold, image baselines below ("RGB only"); columns: k (ours, mean ± std over
    seeds, or the mean alone when n = 1; with `intervals` (see `intervals`) followed by the 95 % bootstrap
    interval ``[lo, hi]``; with `tests` (see `threshold_tests`) a dagger on thresholds significantly below the
    best) then the paper's published number for the GCN rows. Best mean per (method, scenario, k) in bold
    (compared at the printed precision). The csv has ``method, scenario, threshold, k, mean, std, n, [ci_lo,
    ci_hi,] paper[, worse_than_best]``. Returns ``{"table1_md": path, ...}``.
    """
    out_dir = Path(out_dir)
    labels = dict(scenario_labels or {})
    written: dict[str, Path] = {}
    results, intervals, tests = (only_protocol(f, protocol) for f in (results, intervals, tests))
    for metric, (name, _) in TABLES.items():
        name = name + _suffix(protocol)
        if not (results["metric"] == metric).any():
            log.warning("no %s numbers in the results: %s not written", metric, name)
            continue
        short = name.split("_")[0] + _suffix(protocol)
        for ext, text in (("md", _md_table(metric, results, labels, intervals, tests, n_boot)),
                          ("csv", _csv_table(metric, results, intervals, tests)),
                          ("tex", _tex_table(metric, results, labels, intervals, tests, n_boot))):
            path = out_dir / f"{name}.{ext}"
            io.write_text(path, text)
            written[f"{short}_{ext}"] = path
    return written


# ---- figures ---------------------------------------------------------------------------------------------------

def _figure(**kw):
    """A bare `matplotlib.figure.Figure`: rendered by Agg on save, independent of pyplot's (or a notebook's)
    backend, and never left open in pyplot's figure manager."""
    from matplotlib.figure import Figure

    return Figure(**kw)


def _metres(t: float) -> str:
    """'1 m', '∞ m', '0 (no edges)': a threshold in a figure's text."""
    return threshold_label(t) if t == 0 else f"{threshold_label(t)} m"


def _tick(t: float) -> str:
    return threshold_label(t).replace(" (", "\n(")


def fig_recall_vs_threshold(results: pd.DataFrame, path: str | Path, method: str = "gcn", k: int = 1,
                            scenario_labels: Optional[Mapping[str, str]] = None,
                            intervals: Optional[pd.DataFrame] = None, protocol: str = PAPER) -> Path:
    """recall@k against the edge threshold (0: no edges) on one protocol (default ``paper``): one line per
    scenario (mean, error bars = std over seeds, or the 95 % bootstrap interval when `intervals` are given), the
    paper's values as faint dotted lines in the same colour (``paper`` protocol only), image baselines as
    horizontal dashed lines."""
    import matplotlib

    labels = dict(scenario_labels or {})
    results = only_protocol(results if "protocol" in results.columns else results.assign(protocol=PAPER), protocol)
    s = summary(results[(results["metric"] == "recall") & (results["k"] == k)])
    if intervals is not None:
        intervals = only_protocol(intervals if "protocol" in intervals.columns else intervals.assign(protocol=PAPER),
                                  protocol)
        s = s.merge(intervals[SUMMARY_KEYS + ["ci_lo", "ci_hi"]], on=SUMMARY_KEYS, how="left")
    ours = s[(s["method"] == method) & ~s["scenario"].eq(IMAGE_SCENARIO)]
    paper = paper_tables()
    paper = paper[(paper["metric"] == "recall") & (paper["k"] == k)]
    if protocol != PAPER:
        paper = paper.iloc[0:0]
    thresholds = sorted(set(ours["threshold"]) | (set(paper["threshold"]) if method == "gcn" else set()))
    xpos = {t: i for i, t in enumerate(thresholds)}
    scenarios = sorted(ours["scenario"].unique(), key=_natural_key)
    colours = matplotlib.colormaps["tab10"]

    fig = _figure(figsize=(6.4, 4.2))
    ax = fig.subplots()
    for i, sc in enumerate(scenarios):
        g = ours[ours["scenario"] == sc].sort_values("threshold")
        dodge = 0.06 * (i - (len(scenarios) - 1) / 2) if intervals is not None else 0.0
        x = [xpos[t] + dodge for t in g["threshold"]]
        if intervals is not None:
            yerr = np.vstack([g["mean"] - g["ci_lo"], g["ci_hi"] - g["mean"]])
            yerr = np.nan_to_num(yerr, nan=0.0)
        else:
            yerr = g["std"].fillna(0.0).to_numpy()
        ax.errorbar(x, g["mean"], yerr=yerr, color=colours(i), marker="o", capsize=3,
                    label=f"{sc}: {labels.get(sc, sc)}")
        if method == "gcn":
            p = paper[paper["scenario"] == sc].sort_values("threshold")
            if len(p):
                ax.plot([xpos[t] for t in p["threshold"]], p["value"], color=colours(i), linestyle=":", alpha=0.45,
                        marker=".", label=f"{sc} (paper)")
    base = s[[_is_image(m, sc) for m, sc in zip(s["method"], s["scenario"])]]
    for j, (m, g) in enumerate(base.groupby("method", sort=True)):
        ax.axhline(float(g["mean"].mean()), color="0.35", linestyle="--", linewidth=1.2,
                   dashes=(5 + 2 * j, 3), label=f"{m} (RGB only)")
    ax.set_xticks(range(len(thresholds)), [_tick(t) for t in thresholds])
    ax.set_xlabel("edge distance threshold (m)")
    ax.set_ylabel(f"recall@{k} (%)")
    ax.set_ylim(0, 100)
    if intervals is not None:
        spread = f"error bars: 95% bootstrap intervals, {_n_note(s).replace(' (mean only)', '')}"
    else:
        spread = "one seed" if set(s["n"]) <= {1} else f"error bars: std over seeds, {_n_note(s)}"
    where = "" if protocol == PAPER else f", {protocol} protocol"
    ax.set_title(f"{method}: recall@{k} vs edge threshold{where} ({spread})", fontsize=9)
    ax.grid(alpha=0.3)
    handles, names = ax.get_legend_handles_labels()
    rank = lambda name: 1 if name.endswith("(paper)") else 2 if name.endswith("(RGB only)") else 0
    order = sorted(range(len(names)), key=lambda i: (rank(names[i]), i))
    ax.legend([handles[i] for i in order], [names[i] for i in order], fontsize=7, loc="upper left",
              bbox_to_anchor=(1.01, 1.0), frameon=False)
    return io.save_figure(fig, path)


def _read_rankings(cell: Path) -> pd.DataFrame:
    f = cell / "rankings.csv"
    if not f.is_file():
        raise FileNotFoundError(f"{f}: no rankings; is the cell finished?")
    return pd.read_csv(f)


def match_cells(study_name: str, results: Optional[pd.DataFrame] = None, method: str = "gcn",
                threshold: Optional[float] = None, seed: Optional[int] = None) -> dict[str, tuple[float, int, Path]]:
    """``{scenario: (threshold, seed, cell folder)}`` used for Figure 5: per scenario the given threshold, or the
    one with the best mean recall@1 of the ``paper`` protocol (ties: the smallest threshold); the given seed, or
    the smallest one."""
    results = collect(study_name) if results is None else results
    results = only_protocol(results, PAPER)
    r = results[(results["method"] == method) & (results["metric"] == "recall") & (results["k"] == 1)]
    if r.empty:
        raise FileNotFoundError(f"{_cells_root(study_name) / method}: no {method} cell with recall@1")
    out = {}
    for sc in sorted(r["scenario"].unique(), key=_natural_key):
        g = r[r["scenario"] == sc]
        if threshold is not None:
            t = float(threshold)
        else:
            m = g.groupby("threshold")["value"].mean()
            t = float(m[m == m.max()].index.min())
        seeds = sorted(g[g["threshold"] == t]["seed"].unique())
        if not seeds:
            continue
        sd = int(seed) if seed is not None else int(seeds[0])
        out[sc] = (t, sd, paths.cell_dir(study_name, method, sc, t, sd))
    return out


def pick_queries(top1: Mapping[str, pd.DataFrame], n: int = 3) -> list[str]:
    """Deterministic queries for Figure 5 from the top-1 rows of each scenario: two hard ones (fewest scenarios
    right) around an easy one (most scenarios right), each from a different setting (as far as possible)."""
    frames = list(top1.values())
    common = set(frames[0]["query"])
    for f in frames[1:]:
        common &= set(f["query"])
    if not common:
        common = set(frames[0]["query"])
    q = pd.DataFrame({"query": sorted(common)})
    q["setting"] = q["query"].str.split("/").str[0]
    right = np.zeros(len(q), dtype=int)
    for f in frames:
        f = f.drop_duplicates("query").set_index("query")
        right += (f["match_setting"] == f["query_setting"]).reindex(q["query"], fill_value=False).to_numpy(dtype=int)
    q["right"] = right
    easy = q.sort_values(["right", "query"], ascending=[False, True], kind="mergesort")
    hard = q.sort_values(["right", "query"], ascending=[True, True], kind="mergesort")
    chosen: list[str] = []
    used: set[str] = set()
    for pool in [easy] + [hard] * max(0, n - 1):
        pick = pool[~pool["query"].isin(chosen) & ~pool["setting"].isin(used)]
        if pick.empty:
            pick = pool[~pool["query"].isin(chosen)]
        if pick.empty:
            break
        chosen.append(pick["query"].iloc[0])
        used.add(pick["setting"].iloc[0])
    if len(chosen) > 1:       # the paper's layout: a hard one (top), the easy one, the other hard ones
        chosen = [chosen[1], chosen[0], *chosen[2:]]
    return chosen


def _bordered(img: Optional[np.ndarray], colour, shape=(96, 128)) -> np.ndarray:
    if img is None:
        img = np.full((*shape, 3), 128, dtype=np.uint8)
    img = np.asarray(img)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3].astype(np.uint8)
    if colour is None:
        return img
    w = max(2, round(min(img.shape[:2]) / 16))
    out = np.empty((img.shape[0] + 2 * w, img.shape[1] + 2 * w, 3), dtype=np.uint8)
    out[:] = np.asarray(colour, dtype=np.uint8)
    out[w:-w, w:-w] = img
    return out


GREEN, RED = (30, 170, 60), (210, 35, 35)


def fig_matches(study_name: str, rgb_of: RgbOf, path: str | Path, method: str = "gcn",
                results: Optional[pd.DataFrame] = None, threshold: Optional[float] = None,
                seed: Optional[int] = None, queries: Optional[list[str]] = None, n_queries: int = 3,
                scenario_labels: Optional[Mapping[str, str]] = None) -> Path:
    """The paper's Figure 5 (``paper`` protocol): rows = queries, columns = the query then each scenario's top-1
    match, framed green when the match is from the query's setting and red otherwise.

    Cells come from `match_cells` (per scenario the best threshold by mean recall@1 and the smallest seed, unless
    given); queries from `pick_queries` unless given. ``rgb_of(frame_key)`` returns a uint8 (H, W, 3) image (None:
    a grey placeholder).
    """
    labels = dict(scenario_labels or {})
    cells = match_cells(study_name, results, method, threshold, seed)
    top1 = {}
    for sc, (_, _, cell) in cells.items():
        r = split_protocols(_read_rankings(cell))[PAPER]
        top1[sc] = r[r["rank"] == 1].drop_duplicates("query").reset_index(drop=True)
    chosen = list(queries) if queries else pick_queries(top1, n_queries)
    if not chosen:
        raise ValueError(f"{study_name}: no query to show")
    scen = list(cells)
    ncol = 1 + len(scen)
    fig = _figure(figsize=(2.1 * ncol, 1.85 * len(chosen) + 0.4))
    axes = fig.subplots(len(chosen), ncol, squeeze=False)
    for i, q in enumerate(chosen):
        ax = axes[i][0]
        ax.imshow(_bordered(rgb_of(q), None))
        ax.set_ylabel(q.replace("/", "\n", 1), fontsize=6)
        if i == 0:
            ax.set_title("query", fontsize=8)
        for j, sc in enumerate(scen, start=1):
            ax = axes[i][j]
            row = top1[sc][top1[sc]["query"] == q]
            if row.empty:
                ax.imshow(_bordered(None, (160, 160, 160)))
                ax.set_xlabel("not a query here", fontsize=6)
            else:
                row = row.iloc[0]
                ok = row["match_setting"] == row["query_setting"]
                ax.imshow(_bordered(rgb_of(row["match"]), GREEN if ok else RED))
                ax.set_xlabel(str(row["match"]), fontsize=5.5, color="darkgreen" if ok else "darkred")
            if i == 0:
                t, sd, _ = cells[sc]
                ax.set_title(f"{sc}: {labels.get(sc, sc)}\n(t = {_metres(t)}, seed {sd})",
                             fontsize=6.5)
    for ax in np.ravel(axes):
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)
    fig.suptitle(f"Top-1 match per scenario ({method}); green: same setting, red: another setting", fontsize=8)
    fig.tight_layout()
    return io.save_figure(fig, path)


# ---- controlled comparisons: encoder ablation, light, depth scale ----------------------------------------------

def scenario_info(study_name: str, study=None) -> pd.DataFrame:
    """``scenario, depth, semantic, depth_scale, in_tables, label`` of every scenario: from the study when given,
    else from what the cells recorded (``depth``, ``semantic``, ``depth_scale`` (default 1), ``in_tables``
    (default True))."""
    cols = ["scenario", "depth", "semantic", "depth_scale", "in_tables", "label"]
    rows = []
    if study is not None:
        for name, sc in study.scenarios.items():
            rows.append((name, sc.depth, sc.semantic, float(sc.depth_scale), bool(sc.in_tables), sc.label or name))
    else:
        seen = set()
        for f in cell_files(study_name):
            cell = io.read_json(f)
            name = str(cell.get("scenario"))
            if name in seen or name == IMAGE_SCENARIO or cell.get("depth") is None:
                continue
            seen.add(name)
            rows.append((name, str(cell.get("depth")), str(cell.get("semantic")), float(cell.get("depth_scale", 1.0)),
                         bool(cell.get("in_tables", True)), str(cell.get("scenario_label") or name)))
    out = pd.DataFrame(rows, columns=cols)
    return out.sort_values("scenario", key=lambda c: c.map(_natural_key), kind="mergesort").reset_index(drop=True)


def _graph_methods(qv: pd.DataFrame, study=None, base: str = "gcn") -> list[str]:
    present = [m for m in _method_order(qv["method"].unique())
               if not _is_image(m, str(qv.loc[qv["method"] == m, "scenario"].iloc[0]))]
    if study is not None:
        order = [m for m in study.graph_methods() if m in present]
        present = order + [m for m in present if m not in order]
    return ([base] if base in present else []) + [m for m in present if m != base]


def _description(method: str, study=None) -> str:
    from monolib.methods import METHODS

    if study is not None and method in getattr(study, "variants", {}):
        return study.variants[method].description or method
    if study is not None and method in METHODS:
        return METHODS[method][1]
    return method


def _pick_cols(cols: list[str]) -> list[str]:
    """recall@1 and precision@6 when present, else the smallest recall k and the largest precision k."""
    rec = sorted((c for c in cols if c.startswith("recall@")), key=lambda c: _split_metric(c)[1])
    pre = sorted((c for c in cols if c.startswith("precision@")), key=lambda c: _split_metric(c)[1])
    out = []
    if rec:
        out.append("recall@1" if "recall@1" in rec else rec[0])
    if pre:
        out.append("precision@6" if "precision@6" in pre else pre[-1])
    return out


ABLATION_COLUMNS = ["method", "description", "scenario", "threshold", "protocol", "metric", "k", "mean", "ci_lo",
                    "ci_hi", "n_seeds", "diff_vs_base", "diff_lo", "diff_hi", "significant"]


def _with_protocol(frame: pd.DataFrame) -> pd.DataFrame:
    return frame if "protocol" in frame.columns else frame.assign(protocol=PAPER)


def encoder_ablation(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, study=None,
                     base: str = "gcn", protocol: str = PAPER) -> pd.DataFrame:
    """The encoder variants against `base` on every (scenario, threshold) a variant was run at, on one protocol
    (default ``paper``): recall@1 and precision@6 with their intervals, and the paired bootstrap difference to
    `base` (same seeds, settings and queries). Empty when the study has no variant cells. Columns
    `ABLATION_COLUMNS`."""
    qv, iv = only_protocol(_with_protocol(qv), protocol), only_protocol(_with_protocol(iv), protocol)
    if qv.empty:
        return pd.DataFrame(columns=ABLATION_COLUMNS)
    methods = _graph_methods(qv, study, base)
    variants = [m for m in methods if m != base]
    if not variants:
        return pd.DataFrame(columns=ABLATION_COLUMNS)
    vq = qv[qv["method"].isin(variants)]
    combos = sorted({(sc, float(t)) for sc, t in zip(vq["scenario"], vq["threshold"])},
                    key=lambda st: (_natural_key(st[0]), st[1]))
    cols = _pick_cols(_metric_cols(qv))
    ivx = iv.drop(columns="protocol").set_index(["method", "scenario", "threshold", "metric", "k"]).sort_index()
    rows = []
    for m in methods:
        for sc, t in combos:
            mine = _rows_of(qv, m, sc, t)
            if mine.empty:
                continue
            diffs = pd.DataFrame()
            if m != base:
                ref = _rows_of(qv, base, sc, t)
                if not ref.empty:
                    diffs = paired_difference(mine, ref, boot, cols).set_index(["metric", "k"])
            for c in cols:
                metric, k = _split_metric(c)
                key_ = (m, sc, t, metric, k)
                if key_ not in ivx.index:
                    continue
                r = ivx.loc[key_]
                d = diffs.loc[(metric, k)] if (metric, k) in diffs.index else None
                rows.append((m, _description(m, study), sc, t, protocol, metric, k, float(r["mean"]), float(r["ci_lo"]),
                             float(r["ci_hi"]), int(r["n_seeds"]),
                             *((float(d["diff"]), float(d["ci_lo"]), float(d["ci_hi"]), bool(d["significant"]))
                               if d is not None else (np.nan, np.nan, np.nan, False))))
    return pd.DataFrame(rows, columns=ABLATION_COLUMNS)


def _signed(x: float) -> str:
    return f"{x:+.1f}".replace("-", "−") if np.isfinite(x) else "–"


def ablation_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None,
                      base: str = "gcn", n_boot: int = N_BOOT) -> str:
    """``encoder_ablation.md``: rows = method x (scenario, threshold) (the base first), columns = each metric's
    ``mean [lo, hi]`` and its paired difference to the base ``Δ [lo, hi]`` (* when significant)."""
    labels = dict(scenario_labels or {})
    metrics = list(dict.fromkeys(f"{m}@{k}" for m, k in zip(table["metric"], table["k"])))
    head = ["method", "data", "threshold (m)"]
    for c in metrics:
        head += [c, f"Δ {c} vs {base}"]
    lines = [f"**Encoder ablation.** Mean over seeds [95% bootstrap interval: {n_boot} resamples of test settings, "
             f"queries and seeds]. Δ: paired difference to `{base}` on the same seeds, settings and queries "
             f"[95% paired bootstrap interval]; {STAR}: the interval excludes 0 (no correction for multiple "
             f"comparisons).", "",
             "| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * (len(head) - 3)) + "|"]
    prev = None
    for (m, sc, t), g in table.groupby(["method", "scenario", "threshold"], sort=False):
        g = g.assign(col=[f"{a}@{b}" for a, b in zip(g["metric"], g["k"])]).set_index("col")
        line = [f"`{m}`" if m != prev else "", f"{sc}: {labels.get(sc, sc)}", threshold_label(t)]
        prev = m
        for c in metrics:
            if c not in g.index:
                line += ["–", "–"]
                continue
            r = g.loc[c]
            line.append(f"{r['mean']:.1f} {_fmt_ci(r['ci_lo'], r['ci_hi'])}")
            if m == base or not np.isfinite(r["diff_vs_base"]):
                line.append("–")
            else:
                line.append(f"{_signed(r['diff_vs_base'])} [{_signed(r['diff_lo'])}, {_signed(r['diff_hi'])}]"
                            + (STAR if r["significant"] else ""))
        lines.append("| " + " | ".join(line) + " |")
    lines += ["", "Methods:"]
    for m, d in dict(zip(table["method"], table["description"])).items():
        lines.append(f"- `{m}`: {d}")
    return "\n".join(lines) + "\n"


def dim_settings(study_name: str, study=None) -> Optional[dict[str, bool]]:
    """``{setting: dim}`` from the synthetic dataset's ``monolib_synth.json``; None when there is none (a real
    Hypersim download, or a study without a rendered dataset)."""
    root = study.dataset_root if study is not None else paths.study_dir(study_name) / "dataset"
    f = Path(root) / "monolib_synth.json"
    if not f.is_file():
        return None
    return {str(s["name"]): bool(s.get("dim", False)) for s in io.read_json(f).get("settings", [])}


LIGHT_COLUMNS = ["method", "scenario", "threshold", "protocol", "light", "n_settings", "n_queries", "mean", "ci_lo",
                 "ci_hi", "n_seeds"]


def light_table(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, dim_of: Mapping[str, bool],
                scenarios: Optional[list[str]] = None, method: str = "gcn", k: int = 1,
                protocol: str = PAPER) -> pd.DataFrame:
    """recall@k of the queries of dim and of bright test settings: `method` on each scenario (default: every
    scenario it has) at that scenario's best threshold by mean recall@k (ties: the smallest), and every image
    baseline. Rows ``light`` = dim, bright and ``bright - dim`` (the difference of the two resampled means; the two
    sets of settings are drawn independently, the seeds jointly). One protocol (default ``paper``). Columns
    `LIGHT_COLUMNS`."""
    col = f"recall@{k}"
    qv, iv = only_protocol(_with_protocol(qv), protocol), only_protocol(_with_protocol(iv), protocol)
    groups = []
    r = iv[(iv["method"] == method) & (iv["metric"] == "recall") & (iv["k"] == k)]
    for sc in sorted(r["scenario"].unique(), key=_natural_key):
        if scenarios is not None and sc not in scenarios:
            continue
        groups.append((method, sc, _best_threshold(r[r["scenario"] == sc].set_index("threshold")["mean"])))
    for (m, sc, t) in qv[["method", "scenario", "threshold"]].drop_duplicates().itertuples(index=False):
        if _is_image(m, sc):
            groups.append((m, sc, float(t)))
    rows = []
    for m, sc, t in groups:
        g = _rows_of(qv, m, sc, t)
        if col not in g.columns or g[col].isna().any():
            continue
        dim = g["setting"].map(lambda s: bool(dim_of.get(s, False)))
        parts = {}
        offset = 0
        for light, part in (("dim", g[dim.to_numpy()]), ("bright", g[~dim.to_numpy()])):
            if part.empty:
                rows.append((m, sc, t, protocol, light, 0, 0, np.nan, np.nan, np.nan, 0))
                continue
            values, nq = boot.cube(part, [col])
            off = offset if offset + values.shape[1] <= boot.shape[1] else 0
            iv_ = boot.interval(values, nq, off)
            offset += values.shape[1]
            parts[light] = iv_
            rows.append((m, sc, t, protocol, light, int(part["setting"].nunique()), len(part), float(iv_["mean"][0]),
                         float(iv_["ci_lo"][0]), float(iv_["ci_hi"][0]), int(part["seed"].nunique())))
        if len(parts) == 2:
            d = parts["bright"]["boot"][:, 0] - parts["dim"]["boot"][:, 0]
            lo, hi = np.nanpercentile(d, [2.5, 97.5])
            rows.append((m, sc, t, protocol, "bright - dim", int(g["setting"].nunique()), len(g),
                         float(parts["bright"]["mean"][0] - parts["dim"]["mean"][0]), float(lo), float(hi),
                         int(g["seed"].nunique())))
    return pd.DataFrame(rows, columns=LIGHT_COLUMNS)


def fig_recall_by_light(table: pd.DataFrame, path: str | Path, method: str = "gcn", k: int = 1,
                        n_boot: int = N_BOOT) -> Path:
    """Bars: recall@k of queries in bright and in dim test settings per scenario (`method` at each scenario's best
    threshold) and per image baseline; error bars: 95 % bootstrap intervals."""
    t = table[table["light"].isin(["dim", "bright"])]
    groups = list(dict.fromkeys(zip(t["method"], t["scenario"], t["threshold"])))
    fig = _figure(figsize=(max(4.8, 1.1 * len(groups) + 2.0), 3.8))
    ax = fig.subplots()
    width = 0.38
    colours = {"bright": "#f2b134", "dim": "#3b4a6b"}
    for j, light in enumerate(("bright", "dim")):
        xs, ys, err = [], [], [[], []]
        n_set = sorted(set(t[t["light"] == light]["n_settings"]))
        for i, key_ in enumerate(groups):
            r = t[(t["method"] == key_[0]) & (t["scenario"] == key_[1]) & (t["threshold"] == key_[2])
                  & (t["light"] == light)]
            if r.empty or not np.isfinite(r["mean"].iloc[0]):
                continue
            r = r.iloc[0]
            xs.append(i + (j - 0.5) * width)
            ys.append(r["mean"])
            err[0].append(r["mean"] - r["ci_lo"])
            err[1].append(r["ci_hi"] - r["mean"])
        label = f"{light} settings (n = {', '.join(str(int(n)) for n in n_set)})"
        ax.bar(xs, ys, width, yerr=np.asarray(err), capsize=3, color=colours[light], label=label,
               error_kw={"elinewidth": 1.0})
    diff = table[table["light"] == "bright - dim"]
    for i, key_ in enumerate(groups):
        d = diff[(diff["method"] == key_[0]) & (diff["scenario"] == key_[1]) & (diff["threshold"] == key_[2])]
        if len(d) and np.isfinite(d["mean"].iloc[0]):
            d = d.iloc[0]
            ax.text(i, 101, f"Δ {_signed(d['mean'])}\n[{_signed(d['ci_lo'])}, {_signed(d['ci_hi'])}]",
                    ha="center", va="bottom", fontsize=6.5)
    names = [f"{m}\n{sc}, t = {threshold_label(th)}" if not _is_image(m, sc) else f"{m}\n(RGB only)"
             for m, sc, th in groups]
    ax.set_xticks(range(len(groups)), names, fontsize=7)
    ax.set_ylabel(f"recall@{k} (%)")
    ax.set_ylim(0, 116)
    ax.set_yticks(range(0, 101, 20))
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(f"recall@{k}: queries of dim vs bright test settings\n({method} at each scenario's best threshold by "
                 f"mean recall@{k}; error bars: 95% bootstrap intervals, B = {n_boot}; Δ: bright − dim [95% interval])",
                 fontsize=8)
    return io.save_figure(fig, path)


DEPTH_COLUMNS = ["method", "depth", "semantic", "scenario", "depth_scale", "threshold", "protocol", "mean", "ci_lo",
                 "ci_hi", "n_seeds", "diff_vs_scale1", "diff_lo", "diff_hi", "significant"]


def depth_scale_table(qv: pd.DataFrame, iv: pd.DataFrame, boot: Bootstrap, info: pd.DataFrame,
                      method: str = "gcn", k: int = 1, protocol: str = PAPER) -> pd.DataFrame:
    """recall@k against the depth scale factor: the scenarios with ``depth_scale != 1`` and, per (depth,
    semantic) source pair, the scenario with the same sources and scale 1 (the one in the tables first), at
    every threshold `method` was run; with the paired difference to scale 1 at the same threshold. Empty when
    the study has no scaled scenario. One protocol (default ``paper``). Columns `DEPTH_COLUMNS`."""
    col = f"recall@{k}"
    qv, iv = only_protocol(_with_protocol(qv), protocol), only_protocol(_with_protocol(iv), protocol)
    rows = []
    if info.empty:
        return pd.DataFrame(columns=DEPTH_COLUMNS)
    scaled = info[info["depth_scale"] != 1.0]
    r = iv[(iv["method"] == method) & (iv["metric"] == "recall") & (iv["k"] == k)]
    for (depth, semantic), grp in scaled.groupby(["depth", "semantic"], sort=False):
        same = info[(info["depth"] == depth) & (info["semantic"] == semantic)]
        ones = same[same["depth_scale"] == 1.0].sort_values("in_tables", ascending=False, kind="mergesort")
        ref = str(ones["scenario"].iloc[0]) if len(ones) else None
        members = ([ref] if ref else []) + list(grp["scenario"])
        for sc in members:
            scale = float(info.loc[info["scenario"] == sc, "depth_scale"].iloc[0])
            for _, row in r[r["scenario"] == sc].sort_values("threshold").iterrows():
                t = float(row["threshold"])
                d = None
                if ref and sc != ref and not _rows_of(qv, method, ref, t).empty:
                    dd = paired_difference(_rows_of(qv, method, sc, t), _rows_of(qv, method, ref, t), boot, [col])
                    d = dd.iloc[0] if len(dd) else None
                rows.append((method, depth, semantic, sc, scale, t, protocol, float(row["mean"]), float(row["ci_lo"]),
                             float(row["ci_hi"]), int(row["n_seeds"]),
                             *((float(d["diff"]), float(d["ci_lo"]), float(d["ci_hi"]), bool(d["significant"]))
                               if d is not None else (np.nan, np.nan, np.nan, False))))
    out = pd.DataFrame(rows, columns=DEPTH_COLUMNS)
    return out.sort_values(["depth", "semantic", "threshold", "depth_scale"], kind="mergesort").reset_index(drop=True)


def fig_recall_vs_depth_scale(table: pd.DataFrame, path: str | Path, k: int = 1, n_boot: int = N_BOOT) -> Path:
    """recall@k against the depth scale factor (log axis), one line per threshold, one panel per (depth,
    semantic) source pair; error bars: 95 % bootstrap intervals."""
    import matplotlib

    pairs = list(dict.fromkeys(zip(table["depth"], table["semantic"])))
    fig = _figure(figsize=(4.6 * len(pairs) + 1.6, 3.8))
    axes = np.ravel(fig.subplots(1, len(pairs), squeeze=False))
    colours = matplotlib.colormaps["viridis"]
    thresholds = sorted(table["threshold"].unique())
    for ax, (depth, semantic) in zip(axes, pairs):
        g = table[(table["depth"] == depth) & (table["semantic"] == semantic)]
        scales = sorted(g["depth_scale"].unique())
        for i, t in enumerate(thresholds):
            h = g[g["threshold"] == t].sort_values("depth_scale")
            if h.empty:
                continue
            jitter = 1.0 + 0.012 * (i - (len(thresholds) - 1) / 2)
            ax.errorbar(h["depth_scale"] * jitter, h["mean"],
                        yerr=np.vstack([h["mean"] - h["ci_lo"], h["ci_hi"] - h["mean"]]), marker="o", capsize=3,
                        color=colours(i / max(1, len(thresholds) - 1) * 0.9), label=f"t = {_metres(t)}")
        ax.set_xscale("log")
        ax.set_xticks(scales, [f"{s:g}" for s in scales])
        ax.minorticks_off()
        ax.axvline(1.0, color="0.6", linewidth=0.8, linestyle=":")
        ax.set_xlabel("depth scale factor")
        ax.set_ylabel(f"recall@{k} (%)")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
        ax.set_title(f"depth: {depth}, semantics: {semantic}", fontsize=8)
    axes[-1].legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    method = table["method"].iloc[0] if len(table) else "gcn"
    fig.suptitle(f"{method}: recall@{k} vs depth scale (error bars: 95% bootstrap intervals, B = {n_boot})",
                 fontsize=8)
    return io.save_figure(fig, path)


# ---- the two protocols side by side ----------------------------------------------------------------------------

PROTOCOLS_COLUMNS = ["method", "scenario", "threshold", "protocol", "metric", "k", "mean", "ci_lo", "ci_hi",
                     "n_seeds", "n_settings", "n_queries"]


def protocols_table(qv: pd.DataFrame, iv: pd.DataFrame, hidden: frozenset | set = frozenset(), k: int = 1,
                    base: str = PAPER) -> pd.DataFrame:
    """recall@k of every method on every protocol, from the same cells: each graph method on each scenario in the
    tables at the threshold with the best mean recall@k of the `base` protocol (ties: the smallest), every image
    method; with the 95 % bootstrap interval of each protocol (its own resample: the two are not paired) and the
    numbers of settings and queries behind it. Columns `PROTOCOLS_COLUMNS`."""
    iv, qv = _with_protocol(iv), _with_protocol(qv)
    r = iv[(iv["metric"] == "recall") & (iv["k"] == k) & ~iv["scenario"].isin(hidden)]
    groups = []
    for (m, sc), g in r.groupby(["method", "scenario"], sort=False):
        b = g[g["protocol"] == base]
        if b.empty:
            continue
        t = float(b["threshold"].iloc[0]) if _is_image(m, sc) else _best_threshold(b.set_index("threshold")["mean"])
        groups.append((m, sc, t))
    rows = []
    for m, sc, t in groups:
        for _, x in r[(r["method"] == m) & (r["scenario"] == sc) & (r["threshold"] == t)].iterrows():
            q = _rows_of(qv, m, sc, t, x["protocol"])
            n_set = int(q.groupby("seed")["setting"].nunique().max()) if len(q) else 0
            n_q = int(q.groupby("seed").size().max()) if len(q) else 0
            rows.append((m, sc, t, x["protocol"], "recall", k, float(x["mean"]), float(x["ci_lo"]), float(x["ci_hi"]),
                         int(x["n_seeds"]), n_set, n_q))
    out = pd.DataFrame(rows, columns=PROTOCOLS_COLUMNS)
    if out.empty:
        return out
    out["_img"] = [int(_is_image(m, sc)) for m, sc in zip(out["method"], out["scenario"])]
    return _sort(out, ["_img", "scenario", "method", "protocol"]).drop(columns="_img").reset_index(drop=True)


def _group_name(m: str, sc: str, t: float, labels: Mapping[str, str] | None = None) -> str:
    if _is_image(m, sc):
        return f"{m}\n(RGB only)"
    return f"{m}\n{sc}, t = {_metres(t)}"


def protocols_markdown(table: pd.DataFrame, scenario_labels: Optional[Mapping[str, str]] = None,
                       n_boot: int = N_BOOT) -> str:
    """``protocols.md``: one row per method (and scenario), recall@k on each protocol with its interval."""
    labels = dict(scenario_labels or {})
    protos = protocols_in(table)
    k = int(table["k"].iloc[0]) if len(table) else 1
    sizes = {p: (int(g["n_settings"].max()), int(g["n_queries"].max())) for p, g in table.groupby("protocol")}
    head = ["method", "data", "threshold (m)"] + [f"recall@{k} {p} ({sizes[p][0]} settings)" for p in protos]
    lines = [f"**Recall@{k} on both protocols**, from the same trained encoders (cells). `paper`: test settings of "
             f"different families (ai_VVV), the paper's protocol; `siblings`: pairs of settings of one family (same "
             f"furniture and materials, another layout), where a query's candidates include its sibling's frames. "
             f"Graph methods at the threshold with the best `paper` recall@{k} of their scenario. Mean over seeds "
             f"[95% bootstrap interval, {n_boot} resamples of settings, queries and seeds; each protocol resampled "
             f"on its own].", "",
             "| " + " | ".join(head) + " |", "|" + "|".join(["---"] * 3 + ["---:"] * len(protos)) + "|"]
    for (m, sc, t), g in table.groupby(["method", "scenario", "threshold"], sort=False):
        g = g.set_index("protocol")
        image = _is_image(m, sc)
        line = [m, "RGB only" if image else f"{sc}: {labels.get(sc, sc)}", "" if image else threshold_label(t)]
        for p in protos:
            line.append(f"{g.loc[p, 'mean']:.1f} {_fmt_ci(g.loc[p, 'ci_lo'], g.loc[p, 'ci_hi'])}" if p in g.index
                        else "–")
        lines.append("| " + " | ".join(line) + " |")
    return "\n".join(lines) + "\n"


def fig_protocols(table: pd.DataFrame, path: str | Path, k: int = 1, n_boot: int = N_BOOT) -> Path:
    """Bars: recall@k of each method (graph methods per scenario, at the best ``paper`` threshold) on each
    protocol, from the same cells (`protocols_table`); error bars: 95 % bootstrap intervals."""
    import matplotlib

    groups = list(dict.fromkeys(zip(table["method"], table["scenario"], table["threshold"])))
    protos = protocols_in(table)
    fig = _figure(figsize=(max(5.2, 0.95 * len(groups) + 2.4), 3.9))
    ax = fig.subplots()
    width = 0.8 / max(1, len(protos))
    colours = matplotlib.colormaps["tab10"]
    for j, p in enumerate(protos):
        xs, ys, err = [], [], [[], []]
        for i, (m, sc, t) in enumerate(groups):
            r = table[(table["method"] == m) & (table["scenario"] == sc) & (table["threshold"] == t)
                      & (table["protocol"] == p)]
            if r.empty:
                continue
            r = r.iloc[0]
            xs.append(i + (j - (len(protos) - 1) / 2) * width)
            ys.append(r["mean"])
            err[0].append(max(0.0, r["mean"] - r["ci_lo"]))
            err[1].append(max(0.0, r["ci_hi"] - r["mean"]))
        n_set = sorted(set(table.loc[table["protocol"] == p, "n_settings"]))
        ax.bar(xs, ys, width, yerr=np.asarray(err), capsize=2.5, color=colours(j),
               label=f"{p} ({', '.join(str(int(n)) for n in n_set)} settings)", error_kw={"elinewidth": 1.0})
    ax.set_xticks(range(len(groups)), [_group_name(m, sc, t) for m, sc, t in groups], fontsize=6.5)
    ax.set_ylabel(f"recall@{k} (%)")
    ax.set_ylim(0, 100)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, frameon=False, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(f"recall@{k} on both protocols, same trained encoders (graph methods at their best paper-protocol "
                 f"threshold;\nerror bars: 95% bootstrap intervals, B = {n_boot}; siblings: pairs of settings of one "
                 f"family)", fontsize=7.5)
    return io.save_figure(fig, path)


def _csv(df: pd.DataFrame) -> str:
    return df.to_csv(index=False, float_format="%.6g", lineterminator="\n")


# ---- the whole report ------------------------------------------------------------------------------------------

def _load_study(study_name: str):
    """The study of that name from `params/` (None when there is no such file or it does not load)."""
    from monolib import params

    try:
        return params.load_study(study_name, check_files=False)
    except (params.StudyError, OSError) as exc:
        log.info("report of %s without its study file (%s)", study_name, exc)
        return None


def write_report(study_name, rgb_of: Optional[RgbOf] = None,
                 scenario_labels: Optional[Mapping[str, str]] = None, method: str = "gcn", study=None,
                 n_boot: int = N_BOOT) -> dict[str, Path]:
    """Collect a study's cells and write into `monolib.paths.figures_dir(study)`:

    - ``results.csv``: one row per (method, scenario, threshold, seed, protocol, metric, k) number;
    - ``intervals.csv``: per (method, scenario, threshold, protocol, metric, k) the mean and its 95 % bootstrap
      interval over test settings, queries and seeds (`intervals`, ``n_boot`` resamples, numpy seed 0, one
      resample per protocol);
    - ``threshold_tests.csv``: each threshold against its scenario's best (`threshold_tests`), per protocol;
    - Table 1 and 2 (md, csv, tex) of the ``paper`` protocol with the intervals and a dagger on thresholds
      significantly below the best, and the same tables of the ``siblings`` protocol (``table1_recall_siblings.*``,
      ``table2_precision_siblings.*``) when the cells have it; scenarios with ``in_tables: false`` are left out of
      the tables and of ``recall_vs_threshold.png``;
    - ``fig_protocols.png`` + ``protocols.{csv,md}``: recall@1 of each method on both protocols (`protocols_table`;
      when the cells have more than one protocol);
    - ``recall_vs_threshold.png`` (error bars: the intervals) and ``fig5_matches.png`` (skipped when `rgb_of` is
      None or the study has no `method` cell), ``paper`` protocol;
    - ``encoder_ablation.{md,csv}`` when the study has encoder variants (``paper`` protocol);
    - ``recall_by_light.png`` + ``light.csv`` when the dataset records dim settings (``monolib_synth.json``;
      ``paper`` protocol);
    - ``recall_vs_depth_scale.png`` + ``depth_scale.csv`` when the study has scenarios with ``depth_scale != 1``
      (``paper`` protocol).

    `study_name` is a name or a loaded `monolib.params.Study`; `study` (default: ``params/<name>.yaml`` when it
    loads) gives variant descriptions, scenario information and the dataset folder. Labels default to the
    ``scenario_label`` the cells recorded. Returns ``{"results": path, "intervals": path, "table1_md": path, ...}``.
    """
    if not isinstance(study_name, (str, Path)):
        study, study_name = study_name, study_name.name
    study_name = str(study_name)
    if study is None:
        study = _load_study(study_name)
    out = paths.figures_dir(study_name)
    results = collect(study_name)
    labels = {**recorded_labels(study_name), **(labels_of(study) if study is not None else {}),
              **dict(scenario_labels or {})}
    written: dict[str, Path] = {}
    io.write_text(out / "results.csv", results.to_csv(index=False, float_format="%.6g", lineterminator="\n"))
    written["results"] = out / "results.csv"

    try:
        qv_all = query_table(study_name)
    except FileNotFoundError as exc:
        print(f"{study_name}: no per-query rankings, tables without intervals ({exc})")
        qv_all = None
    protos = protocols_in(results)
    iv_all = tests = qv = iv = boot = None
    if qv_all is not None:
        ivs, tts, boots = [], [], {}
        for p in protocols_in(qv_all):  # each protocol resampled on its own: nothing is paired across protocols
            qp = only_protocol(qv_all, p)
            boots[p] = Bootstrap.for_queries(qp, n_boot)
            ivs.append(intervals(qp, boots[p]))
            tts.append(threshold_tests(qp, ivs[-1], boots[p]))
        iv_all = _sort(pd.concat(ivs, ignore_index=True), SUMMARY_KEYS)
        tests = pd.concat(tts, ignore_index=True)
        io.write_text(out / "intervals.csv", _csv(iv_all))
        written["intervals"] = out / "intervals.csv"
        io.write_text(out / "threshold_tests.csv", _csv(tests))
        written["threshold_tests"] = out / "threshold_tests.csv"
        if PAPER in boots:  # the controlled comparisons below: the paper protocol
            qv, iv, boot = only_protocol(qv_all, PAPER), only_protocol(iv_all, PAPER), boots[PAPER]

    info = scenario_info(study_name, study)
    hidden = set(info.loc[~info["in_tables"].astype(bool), "scenario"])
    in_tables = results[~results["scenario"].isin(hidden)]
    for p in protos:
        written.update(write_tables(in_tables, out, labels, iv_all, tests, n_boot, protocol=p))
    written["recall_vs_threshold"] = fig_recall_vs_threshold(in_tables, out / "recall_vs_threshold.png", method,
                                                             scenario_labels=labels, intervals=iv_all)
    if rgb_of is not None and (in_tables["method"] == method).any():
        written["fig5_matches"] = fig_matches(study_name, rgb_of, out / "fig5_matches.png", method,
                                              results=in_tables, scenario_labels=labels)
    if qv_all is not None and len(protocols_in(qv_all)) > 1:
        table = protocols_table(qv_all, iv_all, hidden)
        io.write_text(out / "protocols.csv", _csv(table))
        io.write_text(out / "protocols.md", protocols_markdown(table, labels, n_boot))
        written["protocols_csv"], written["protocols_md"] = out / "protocols.csv", out / "protocols.md"
        written["fig_protocols"] = fig_protocols(table, out / "fig_protocols.png", n_boot=n_boot)
    else:
        print(f"{study_name}: one protocol only (protocol.siblings: 0): fig_protocols.png not drawn")

    if qv is None:
        log.info("report of %s written to %s", study_name, out)
        return written
    ablation = encoder_ablation(qv, iv, boot, study, base=method)
    if len(ablation):
        io.write_text(out / "encoder_ablation.md", ablation_markdown(ablation, labels, method, n_boot))
        io.write_text(out / "encoder_ablation.csv", _csv(ablation))
        written["encoder_ablation_md"] = out / "encoder_ablation.md"
        written["encoder_ablation_csv"] = out / "encoder_ablation.csv"

    dim_of = dim_settings(study_name, study)
    if dim_of is None:
        print(f"{study_name}: no monolib_synth.json with dim settings: recall_by_light.png not drawn")
    elif not any(dim_of.get(s, False) for s in qv["setting"].unique()):
        print(f"{study_name}: no dim test setting among the queries: recall_by_light.png not drawn")
    else:
        shown = [sc for sc in qv["scenario"].unique() if sc not in hidden]
        light = light_table(qv, iv, boot, dim_of, shown, method)
        io.write_text(out / "light.csv", _csv(light))
        written["light"] = out / "light.csv"
        written["recall_by_light"] = fig_recall_by_light(light, out / "recall_by_light.png", method, n_boot=n_boot)

    depth = depth_scale_table(qv, iv, boot, info, method)
    if depth.empty:
        print(f"{study_name}: no scenario with depth_scale != 1 (and {method} cells): recall_vs_depth_scale.png "
              f"not drawn")
    else:
        io.write_text(out / "depth_scale.csv", _csv(depth))
        written["depth_scale"] = out / "depth_scale.csv"
        written["recall_vs_depth_scale"] = fig_recall_vs_depth_scale(depth, out / "recall_vs_depth_scale.png",
                                                                     n_boot=n_boot)
    log.info("report of %s written to %s", study_name, out)
    return written
