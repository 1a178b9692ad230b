"""The report's statistics engine: means over seeds, bootstrap intervals and paired differences, which the tables
of `monolib.report.comparisons` (thresholds against the best, the controlled comparisons) are built on.

Uncertainty
-----------
Every number of the tables is a mean over seeds of a mean over the queries of the test settings. Its 95 %
interval comes from a hierarchical bootstrap over the three sources of variation: per resample, the seeds are
drawn with replacement, the settings are drawn with replacement, and within each drawn (seed, setting) its
queries are drawn with replacement; the statistic is the mean of the drawn per-query values (recall@k: a hit
indicator x 100; precision@k: the own-setting share of the top k x 100; `monolib.report.results.per_query_values`). The
interval is the 2.5 and 97.5 percentiles over B resamples (`Bootstrap`, `intervals`; ``intervals.csv``).

The resample *indices* are one fixed set per study (`Bootstrap`, numpy seed 0): uniform numbers drawn once for
[B, seed slot], [B, setting slot] and [B, seed slot, setting slot, query slot], turned into indices by
floor(u * n). Every cell group of a study is resampled with the same numbers, and as the protocol draw
depends only on the seed (same queries in every method, scenario and threshold of a seed), two groups resampled
with the same numbers are paired: the difference of their resampled means is the paired bootstrap of the
difference (`paired_difference` joins the per-query values on seed, setting and query first, so a group against
itself gives exactly 0). Thresholds significantly below their scenario's best are found with it
(`monolib.report.comparisons.threshold_tests`; ``threshold_tests.csv``), and so are the differences of the
controlled comparisons.

Every statistic is computed within one protocol (its own bootstrap; nothing is paired across protocols).

Folds by volume add a level above the seeds (`FoldBootstrap`, `fold_intervals`, `fold_paired_difference`): per
resample the folds are drawn with replacement, then each drawn fold's seeds, settings and queries as above.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import numpy as np
import pandas as pd

from monolib.params import PAPER
from monolib.report.results import SUMMARY_KEYS, metric_cols, only_protocol, sort_rows, split_metric

N_BOOT = 1000
BOOT_SEED = 0
GROUP_KEYS = ["method", "scenario", "threshold", "protocol"]
INTERVAL_COLUMNS = ["method", "scenario", "threshold", "protocol", "metric", "k", "mean", "ci_lo", "ci_hi", "n_seeds"]


# ---- mean and spread over seeds --------------------------------------------------------------------------------

def summary(results: pd.DataFrame) -> pd.DataFrame:
    """Mean, sample std (ddof 1; NaN when n = 1) and n over seeds per (method, scenario, threshold, protocol,
    metric, k) of `monolib.report.results.collect`."""
    keys = [k for k in SUMMARY_KEYS if k in results.columns]
    g = results.groupby(keys, sort=False)["value"]
    out = g.agg(mean="mean", std="std", n="count").reset_index()
    return sort_rows(out, keys)


# ---- the bootstrap over test settings, queries and seeds -------------------------------------------------------

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
        """Sized for every group of a `monolib.report.results.query_table`."""
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
        rows = values.reshape(r * s * q, m)  # drawn by one flat index (np.take: a third of fancy indexing's time)
        counts = np.ascontiguousarray(nq).reshape(r * s)
        for b0 in range(0, self.n_boot, step):
            b1 = min(self.n_boot, b0 + step)
            rs = np.minimum((self.u_seed[b0:b1, :r] * r).astype(np.intp), r - 1)                       # [b, R]
            gs = np.minimum((self.u_setting[b0:b1, offset:offset + s] * s).astype(np.intp), s - 1)      # [b, S]
            cell = rs[:, :, None] * s + gs[:, None, :]                                                 # [b, R, S]
            n = counts[cell]
            qi = (self.u_query[b0:b1, :r, offset:offset + s, :q] * n[..., None]).astype(np.intp)       # [b, R, S, Q]
            np.minimum(qi, np.maximum(n - 1, 0)[..., None], out=qi)  # u < 1, yet u * n can round up to n
            valid = (slots < n[..., None]).astype(float)
            drawn = np.take(rows, cell[..., None] * q + qi, axis=0)                                    # [b, R, S, Q, M]
            with np.errstate(invalid="ignore", divide="ignore"):
                out[b0:b1] = np.einsum("brsqm,brsq->bm", drawn, valid) / valid.sum(axis=(1, 2, 3))[:, None]
        return out

    def interval(self, values: np.ndarray, nq: np.ndarray, offset: int = 0) -> dict[str, np.ndarray]:
        """``{"mean", "ci_lo", "ci_hi", "boot"}`` per metric (percentiles 2.5 and 97.5 of the resampled means)."""
        boot = self.resample(values, nq, offset)
        lo, hi = np.nanpercentile(boot, [2.5, 97.5], axis=0)
        return {"mean": self.observed(values, nq), "ci_lo": lo, "ci_hi": hi, "boot": boot}


class FoldBootstrap:
    """`Bootstrap` with a fold level above it, for studies cross-validated by volume: per resample the folds are
    drawn with replacement and each drawn fold contributes its own (seed, setting, query) resample; the statistic
    is the mean over the drawn folds (each fold weighs the same, whatever its number of settings). A fold's
    settings use their own slots of the underlying `Bootstrap` (`offset`), so two folds never share setting or
    query draws; the seeds, crossed with the folds (the same seeds train every fold), share theirs. The fold draws
    come from their own numpy stream (`BOOT_SEED`, 1), so the study's other intervals keep their numbers.
    Resampled with the same numbers, two groups of the same folds are paired (`fold_paired_difference`)."""

    def __init__(self, n_folds: int, n_seeds: int, settings_per_fold: int, n_queries: int, n_boot: int = N_BOOT,
                 seed: int = BOOT_SEED):
        self.n_folds, self.settings_per_fold = int(n_folds), int(settings_per_fold)
        self.boot = Bootstrap(n_seeds, self.n_folds * self.settings_per_fold, n_queries, n_boot, seed)
        self.u_fold = np.random.default_rng([seed, 1]).random((self.boot.n_boot, self.n_folds))

    @classmethod
    def for_queries(cls, qv: pd.DataFrame, n_boot: int = N_BOOT, seed: int = BOOT_SEED) -> "FoldBootstrap":
        """Sized for every group of a per-query table with a ``fold`` column."""
        keys = [k for k in GROUP_KEYS if k in qv.columns] + ["fold"]
        return cls(int(qv["fold"].nunique()), int(qv.groupby(keys)["seed"].nunique().max()),
                   int(qv.groupby(keys + ["seed"])["setting"].nunique().max()),
                   int(qv.groupby(keys + ["seed", "setting"]).size().max()), n_boot, seed)

    def cubes(self, frame: pd.DataFrame, cols: list[str]) -> list[tuple[np.ndarray, np.ndarray]]:
        """One `Bootstrap.cube` per fold of `frame` (folds in sorted order)."""
        return [Bootstrap.cube(g, cols) for _, g in sorted(frame.groupby("fold"), key=lambda kv: kv[0])]

    def interval(self, cubes: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
        """``{"mean", "ci_lo", "ci_hi", "boot"}`` per metric: the mean over folds of each fold's mean, and the
        percentiles 2.5 and 97.5 of the fold-level resample."""
        if len(cubes) > self.n_folds:
            raise ValueError(f"fold bootstrap sized for {self.n_folds} folds, got {len(cubes)}")
        per = np.stack([self.boot.resample(v, nq, offset=f * self.settings_per_fold)
                        for f, (v, nq) in enumerate(cubes)])                                    # [F, B, M]
        n = len(cubes)
        drawn = np.minimum((self.u_fold[:, :n] * n).astype(np.intp), n - 1)                    # [B, F]
        boot = per[drawn, np.arange(per.shape[1])[:, None]].mean(axis=1)                       # [B, M]
        lo, hi = np.nanpercentile(boot, [2.5, 97.5], axis=0)
        mean = np.mean([Bootstrap.observed(v, nq) for v, nq in cubes], axis=0)
        return {"mean": mean, "ci_lo": lo, "ci_hi": hi, "boot": boot}


def fold_intervals(qv: pd.DataFrame, fboot: FoldBootstrap) -> pd.DataFrame:
    """`intervals` over folds: per (method, scenario, threshold, protocol, metric, k) the mean over folds and
    seeds and its 95 % interval resampling folds, settings, queries and seeds (`FoldBootstrap`); `qv`: per-query
    rows with a ``fold`` column. Columns `INTERVAL_COLUMNS` + ``n_folds``."""
    rows = []
    for (method, scenario, threshold, protocol), g in qv.groupby(GROUP_KEYS, sort=False):
        cols = _group_cols(g)
        if not cols:
            continue
        iv = fboot.interval(fboot.cubes(g, cols))
        for j, c in enumerate(cols):
            metric, k = split_metric(c)
            rows.append((method, scenario, float(threshold), protocol, metric, k, float(iv["mean"][j]),
                         float(iv["ci_lo"][j]), float(iv["ci_hi"][j]), int(g["seed"].nunique()),
                         int(g["fold"].nunique())))
    return sort_rows(pd.DataFrame(rows, columns=INTERVAL_COLUMNS + ["n_folds"]), SUMMARY_KEYS)


def fold_paired_difference(a: pd.DataFrame, b: pd.DataFrame, fboot: FoldBootstrap,
                           cols: Optional[list[str]] = None) -> pd.DataFrame:
    """`paired_difference` over folds: mean(a) - mean(b) over the (fold, seed, setting, query) rows the two share,
    resampled with `FoldBootstrap`. Columns of `paired_difference` + ``n_folds``."""
    d, cols = _paired(a, b, ["fold", "seed", "setting", "query"], cols)
    rows = []
    if len(d) and cols:
        iv = fboot.interval(fboot.cubes(d, cols))
        for i, c in enumerate(cols):
            lo, hi = float(iv["ci_lo"][i]), float(iv["ci_hi"][i])
            rows.append((*split_metric(c), float(iv["mean"][i]), lo, hi, bool(lo > 0 or hi < 0),
                         int(d["seed"].nunique()), len(d), int(d["fold"].nunique())))
    return pd.DataFrame(rows, columns=["metric", "k", "diff", "ci_lo", "ci_hi", "significant", "n_seeds",
                                       "n_queries", "n_folds"])


STABILITY_RESAMPLES = 100  # resamples of the seeds a claim's verdict is recomputed on (`seed_resampled_intervals`)


def seed_resampled_intervals(a: pd.DataFrame, b: pd.DataFrame, boot, cols: list[str],
                             n: int = STABILITY_RESAMPLES, seed: int = BOOT_SEED) -> np.ndarray:
    """[n, 2]: the (lo, hi) 95 % interval of the paired difference mean(a) - mean(b) (`paired_difference`, or
    `fold_paired_difference` when `boot` is a `FoldBootstrap`) recomputed on `n` resamples of the seeds with
    replacement (numpy stream ``[seed, 2]``; a seed drawn twice counts twice; with folds the same seeds in every
    fold, as the same seeds train every fold). What another draw of the study's seeds could have given: the share
    of resamples in which a claim's verdict stays is its stability. Empty (0 rows) with fewer than two seeds.
    `cols`: one metric column."""
    folds = isinstance(boot, FoldBootstrap)
    keys = (["fold"] if folds else []) + ["seed", "setting", "query"] + (
        ["protocol"] if not folds and "protocol" in a.columns and "protocol" in b.columns else [])
    d, cols = _paired(a, b, keys, cols)
    n_seeds = int(d["seed"].nunique()) if len(d) else 0
    if n_seeds < 2 or not cols:
        return np.empty((0, 2))
    draws = np.random.default_rng([seed, 2]).integers(0, n_seeds, size=(n, n_seeds))
    cubes = boot.cubes(d, cols) if folds else [boot.cube(d, cols)]

    def bounds(idx: np.ndarray) -> tuple[float, float]:
        drawn = [(v[idx], nq[idx]) for v, nq in cubes]
        iv = boot.interval(drawn) if folds else boot.interval(*drawn[0])
        return float(iv["ci_lo"][0]), float(iv["ci_hi"][0])

    # numpy's array loops release the GIL: the resamples run on the CPU's cores, each on its own arrays, so the
    # result is the same on any number of threads
    with ThreadPoolExecutor(max_workers=max(1, min(os.cpu_count() or 1, 8))) as pool:
        return np.array(list(pool.map(bounds, draws)), dtype=float).reshape(n, 2)


def rows_of(qv: pd.DataFrame, method: str, scenario: str, threshold: float,
            protocol: Optional[str] = None) -> pd.DataFrame:
    """The per-query rows of one (method, scenario, threshold) group (of one protocol when given)."""
    rows = qv[(qv["method"] == method) & (qv["scenario"] == scenario) & (qv["threshold"] == threshold)]
    return rows if protocol is None else only_protocol(rows, protocol)


def _group_cols(frame: pd.DataFrame, cols: Optional[list[str]] = None) -> list[str]:
    cols = metric_cols(frame) if cols is None else cols
    return [c for c in cols if c in frame.columns and frame[c].notna().all()]


def intervals(qv: pd.DataFrame, boot: Bootstrap) -> pd.DataFrame:
    """``intervals.csv``: per (method, scenario, threshold, protocol, metric, k) the mean and its 95 % bootstrap
    interval, and the number of seeds (columns `INTERVAL_COLUMNS`). Pass one protocol's rows with its own
    `Bootstrap` (as `monolib.report.write.write_report` does) for intervals independent of the other protocol."""
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
            metric, k = split_metric(c)
            rows.append((method, scenario, float(threshold), protocol, metric, k, float(iv["mean"][j]),
                         float(iv["ci_lo"][j]), float(iv["ci_hi"][j]), int(g["seed"].nunique())))
    out = pd.DataFrame(rows, columns=INTERVAL_COLUMNS)
    return sort_rows(out, SUMMARY_KEYS)


# ---- paired tests ----------------------------------------------------------------------------------------------

def _paired(a: pd.DataFrame, b: pd.DataFrame, keys: list[str], cols: Optional[list[str]]) -> tuple:
    """``(per-query differences a - b on the rows the two share (joined on `keys`), the metric columns)``."""
    cols = [c for c in (_group_cols(a, cols)) if c in _group_cols(b, cols)]
    j = a[keys + cols].merge(b[keys + cols], on=keys, how="inner", suffixes=("_a", "_b"), validate="one_to_one")
    d = j[keys].drop(columns="protocol", errors="ignore").copy()
    for c in cols:
        d[c] = j[f"{c}_a"].to_numpy(dtype=float) - j[f"{c}_b"].to_numpy(dtype=float)
    return d, cols


def paired_difference(a: pd.DataFrame, b: pd.DataFrame, boot: Bootstrap,
                      cols: Optional[list[str]] = None) -> pd.DataFrame:
    """Paired bootstrap of mean(a) - mean(b) over the (seed, setting, query) triples the two share.

    `a` and `b` are per-query rows (``seed, setting, query`` + metric columns), e.g. two cells groups of one
    study. Returns one row per metric column: ``metric, k, diff, ci_lo, ci_hi, significant`` (the interval
    excludes 0), and ``n_seeds``, ``n_queries`` of the shared rows.
    """
    keys = ["seed", "setting", "query"] + (["protocol"] if "protocol" in a.columns and "protocol" in b.columns else [])
    d, cols = _paired(a, b, keys, cols)
    rows = []
    if len(d) and cols:
        values, nq = boot.cube(d, cols)
        iv = boot.interval(values, nq)
        for i, c in enumerate(cols):
            lo, hi = float(iv["ci_lo"][i]), float(iv["ci_hi"][i])
            rows.append((*split_metric(c), float(iv["mean"][i]), lo, hi, bool(lo > 0 or hi < 0),
                         int(d["seed"].nunique()), len(d)))
    return pd.DataFrame(rows, columns=["metric", "k", "diff", "ci_lo", "ci_hi", "significant", "n_seeds", "n_queries"])
