"""The paper's evaluation protocol, nearest-neighbour retrieval and recall@k / precision@k.

Per test setting, `queries` frames are queries and `positives` are positives (a seeded random draw). A query's
candidates are its own setting's positives plus every frame of the other settings; its own setting's queries
(itself included) are never candidates. Recall@k: share of queries with a frame of their setting in the top k.
Precision@k: mean over queries of (frames of their setting in the top k) / k. Distances: Euclidean.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from monolib.params import Protocol


@dataclass
class Draw:
    """Which test frames are queries (True) and which are positives (False)."""
    frames: list[str]        # frame keys, in embedding order
    settings: np.ndarray     # (N,) setting of each frame
    is_query: np.ndarray     # (N,) bool

    def table(self) -> pd.DataFrame:
        return pd.DataFrame({"frame": self.frames, "setting": self.settings,
                             "role": np.where(self.is_query, "query", "positive")})


def draw_protocol(frames: list[str], settings, protocol: Protocol, seed: int) -> Draw:
    """Seeded draw of `protocol.queries` queries and `protocol.positives` positives per setting."""
    settings = np.asarray(settings)
    rng = np.random.default_rng(seed)
    is_query = np.zeros(len(frames), bool)
    names = sorted(set(settings))
    if len(names) != protocol.settings:
        raise ValueError(f"protocol: {protocol.settings} test settings expected, got {len(names)}")
    for name in names:  # one loop over settings (16), not over queries
        idx = np.flatnonzero(settings == name)
        if len(idx) != protocol.frames:
            raise ValueError(f"protocol: setting {name} has {len(idx)} frames, {protocol.frames} expected")
        is_query[rng.permutation(idx)[: protocol.queries]] = True
    return Draw(list(frames), settings, is_query)


def rank(embeddings: torch.Tensor | np.ndarray, draw: Draw, k: int = 10, use_faiss: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-k candidates of every query: (query indices (Q,), match indices (Q, k), distances (Q, k)).

    `torch.cdist` + `topk` over all queries at once; forbidden candidates get distance +inf.
    """
    emb = torch.as_tensor(np.asarray(embeddings, dtype=np.float32)) if not torch.is_tensor(embeddings) else embeddings.float()
    q = np.flatnonzero(draw.is_query)
    codes = np.unique(draw.settings, return_inverse=True)[1]
    d = torch.cdist(emb[torch.as_tensor(q)], emb)
    forbidden = (codes[q][:, None] == codes[None, :]) & draw.is_query[None, :]
    d[torch.as_tensor(forbidden)] = float("inf")
    k = min(k, int((~forbidden).sum(axis=1).min()))
    dist, idx = torch.topk(d, k, dim=1, largest=False, sorted=True)
    return q, idx.numpy(), dist.numpy()


def rankings_table(draw: Draw, q: np.ndarray, idx: np.ndarray, dist: np.ndarray) -> pd.DataFrame:
    """The `rankings.csv` of a cell: query, query_setting, rank (from 1), match, match_setting, distance."""
    Q, k = idx.shape
    frames = np.asarray(draw.frames)
    return pd.DataFrame({
        "query": np.repeat(frames[q], k),
        "query_setting": np.repeat(draw.settings[q], k),
        "rank": np.tile(np.arange(1, k + 1), Q),
        "match": frames[idx.ravel()],
        "match_setting": draw.settings[idx.ravel()],
        "distance": dist.ravel().astype(np.float64),
    })


def metrics_from_hits(hits: np.ndarray, recall_k, precision_k) -> dict[str, float]:
    """hits (Q, K) bool: rank r of query q is from q's setting. Percentages."""
    out = {}
    for k in recall_k:
        out[f"recall@{k}"] = float(100.0 * hits[:, :k].any(axis=1).mean())
    for k in precision_k:
        out[f"precision@{k}"] = float(100.0 * (hits[:, :k].sum(axis=1) / k).mean())
    return out


def evaluate(embeddings, frames: list[str], settings, protocol: Protocol, seed: int):
    """The whole protocol: (metrics dict in percent, rankings DataFrame, the Draw)."""
    draw = draw_protocol(frames, settings, protocol, seed)
    kmax = max(list(protocol.recall_k) + list(protocol.precision_k) + [10])
    q, idx, dist = rank(embeddings, draw, kmax)
    hits = draw.settings[idx] == draw.settings[q][:, None]
    return metrics_from_hits(hits, protocol.recall_k, protocol.precision_k), rankings_table(draw, q, idx, dist), draw
