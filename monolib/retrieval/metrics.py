"""Recall@k and precision@k, the one definition: from the hits of a ranking (`metrics_from_hits`, what a cell
computes) or from a cell's ``rankings.csv`` (`metrics_from_rankings`, any k up to the rankings' depth, what the
report and a finished cell's new k read). No torch: the report imports it.
"""
from __future__ import annotations

import numpy as np
import pandas as pd


def metrics_from_hits(hits: np.ndarray, recall_k, precision_k) -> dict[str, float]:
    """hits (Q, K) bool: rank r of query q is from q's setting. Percentages."""
    out = {}
    for k in recall_k:
        out[f"recall@{k}"] = float(100.0 * hits[:, :k].any(axis=1).mean())
    for k in precision_k:
        out[f"precision@{k}"] = float(100.0 * (hits[:, :k].sum(axis=1) / k).mean())
    return out


def metric_names(recall_k, precision_k) -> list[str]:
    """``recall@k`` then ``precision@k`` for each k: the keys of a cell's metrics."""
    return [f"recall@{int(k)}" for k in recall_k] + [f"precision@{int(k)}" for k in precision_k]


def hit_matrix(rankings: pd.DataFrame) -> tuple[pd.Index, np.ndarray]:
    """(queries, hits) of one protocol's rankings (`rankings_table`): ``hits[i, r]`` is True when query i's rank
    r+1 candidate is from the query's setting."""
    codes, queries = pd.factorize(rankings["query"], sort=True)
    ranks = rankings["rank"].to_numpy(dtype=int)
    if len(ranks) and ranks.min() < 1:
        raise ValueError("rankings: ranks start at 1")
    hits = np.zeros((len(queries), int(ranks.max()) if len(ranks) else 0), dtype=bool)
    hits[codes, ranks - 1] = rankings["match_setting"].to_numpy() == rankings["query_setting"].to_numpy()
    return queries, hits


def metrics_from_rankings(rankings: pd.DataFrame, recall_k, precision_k,
                          positives_per_setting=None) -> dict[str, float]:
    """`metrics_from_hits` of one protocol's rankings: what `evaluate` returned for them, at any k up to their
    depth (`ranking_depth`), so that a new k is computed from a finished cell without training.

    ``positives_per_setting`` None (default, the paper's definition): precision@k divides by k. Given (one number,
    or a mapping setting -> number of positives), it divides by ``min(k, positives of the query's setting)``, the
    best reachable share when a setting has fewer positives than k. Raises ValueError when a k exceeds the
    depth of the rankings or there is no query."""
    queries, hits = hit_matrix(rankings)
    recall_k, precision_k = [int(k) for k in recall_k], [int(k) for k in precision_k]
    ks = recall_k + precision_k
    if ks and max(ks) > hits.shape[1]:
        raise ValueError(f"rankings: k={max(ks)} needs the top {max(ks)}, the rankings hold the top {hits.shape[1]}")
    if len(queries) == 0:
        raise ValueError("rankings: no query")
    if positives_per_setting is None:
        return metrics_from_hits(hits, recall_k, precision_k)
    setting_of = rankings.drop_duplicates("query").set_index("query")["query_setting"].reindex(queries)
    if isinstance(positives_per_setting, (int, np.integer, float)):
        npos = np.full(len(queries), float(positives_per_setting))
    else:
        npos = setting_of.map(pd.Series(positives_per_setting)).to_numpy(dtype=float)
        if np.isnan(npos).any():
            raise ValueError(f"positives_per_setting: no count for settings "
                             f"{sorted(set(setting_of[np.isnan(npos)]))}")
    found = np.cumsum(hits, axis=1)  # own-setting frames within the top r+1
    out = metrics_from_hits(hits, recall_k, [])
    for k in precision_k:
        out[f"precision@{k}"] = float(100.0 * np.mean(found[:, k - 1] / np.minimum(k, npos)))
    return out
