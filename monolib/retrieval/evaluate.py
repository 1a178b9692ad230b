"""The paper's evaluation protocol, nearest-neighbour retrieval and recall@k / precision@k.

Per test setting, `queries` frames are queries and `positives` are positives (a seeded random draw). A query's
candidates are its own setting's positives plus every frame of the protocol's other settings; its own setting's
queries (itself included) are never candidates. Recall@k: share of queries with a frame of their setting in the
top k. Precision@k: mean over queries of (frames of their setting in the top k) / k. Distances: Euclidean.

Two protocols share the test frames and the trained encoders (`protocol_settings`): ``paper`` (`settings` test
settings of as many different families, the paper's protocol) and ``siblings`` (`siblings` families of two
settings each: same furniture and materials, another layout; the paper's "two neighbouring offices"). A setting's
family is the ``ai_VVV`` part of its name (`family`), a Hypersim volume. Each protocol is drawn and evaluated on its
own settings' frames only, with its own seed (`protocol_seed`).
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from monolib.data.protocols import ProtocolDataError, protocol_settings
from monolib.params import Protocol
from monolib.retrieval.metrics import metrics_from_hits


def ranking_depth(protocol: Protocol) -> int:
    """How many candidates a cell's rankings keep per query: the largest k of the metrics, at least 10."""
    return max(list(protocol.recall_k) + list(protocol.precision_k) + [10])


def protocol_seed(seed: int, name: str) -> int:
    """The seed of a protocol's draw: derived from the cell seed and the protocol's name (deterministic)."""
    ss = np.random.SeedSequence([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode())])
    return int(ss.generate_state(1, np.uint32)[0])


@dataclass
class Draw:
    """Which test frames are queries (True) and which are positives (False)."""
    frames: list[str]        # frame keys, in embedding order
    settings: np.ndarray     # (N,) setting of each frame
    is_query: np.ndarray     # (N,) bool

    def table(self) -> pd.DataFrame:
        return pd.DataFrame({"frame": self.frames, "setting": self.settings,
                             "role": np.where(self.is_query, "query", "positive")})


def draw_protocol(frames: list[str], settings, protocol: Protocol, seed: int, n_settings: int | None = None) -> Draw:
    """Seeded draw of `protocol.queries` queries and `protocol.positives` positives per setting, over exactly
    `n_settings` settings (default `protocol.settings`)."""
    settings = np.asarray(settings)
    rng = np.random.default_rng(seed)
    is_query = np.zeros(len(frames), bool)
    names = sorted(set(settings))
    expected = protocol.settings if n_settings is None else n_settings
    if len(names) != expected:
        raise ProtocolDataError(f"protocol: {expected} test settings expected, got {len(names)}")
    for name in names:  # one loop over settings (16), not over queries
        idx = np.flatnonzero(settings == name)
        if len(idx) != protocol.frames:
            raise ProtocolDataError(f"protocol: setting {name} has {len(idx)} frames, {protocol.frames} expected")
        is_query[rng.permutation(idx)[: protocol.queries]] = True
    return Draw(list(frames), settings, is_query)


def rank(embeddings: torch.Tensor | np.ndarray, draw: Draw, k: int = 10,
         use_faiss: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-k candidates of every query: (query indices (Q,), match indices (Q, k), distances (Q, k)).

    `torch.cdist` + `topk` over all queries at once; forbidden candidates get distance +inf.
    """
    emb = (torch.as_tensor(np.asarray(embeddings, dtype=np.float32)) if not torch.is_tensor(embeddings)
           else embeddings.float())
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


def evaluate(embeddings, frames: list[str], settings, protocol: Protocol, seed: int, n_settings: int | None = None):
    """One protocol on exactly these frames: (metrics dict in percent, rankings DataFrame, the Draw)."""
    draw = draw_protocol(frames, settings, protocol, seed, n_settings)
    kmax = ranking_depth(protocol)
    q, idx, dist = rank(embeddings, draw, kmax)
    hits = draw.settings[idx] == draw.settings[q][:, None]
    return metrics_from_hits(hits, protocol.recall_k, protocol.precision_k), rankings_table(draw, q, idx, dist), draw


@dataclass
class ProtocolResult:
    name: str                # paper | siblings
    settings: list[str]      # the protocol's test settings
    seed: int                # the seed of its draw (`protocol_seed`)
    metrics: dict[str, float]
    rankings: pd.DataFrame   # `rankings_table` with a leading ``protocol`` column
    draw: Draw

    def protocol_table(self) -> pd.DataFrame:
        """The protocol's part of ``protocol.csv``: protocol, frame, setting, role."""
        t = self.draw.table()
        t.insert(0, "protocol", self.name)
        return t


def evaluate_protocols(embeddings, frames: list[str], settings, protocol: Protocol,
                       seed: int) -> dict[str, ProtocolResult]:
    """Every protocol of the study (``paper``; ``siblings`` when `protocol.siblings` > 0) on the embeddings of the test
    frames (the union of the protocols' settings): each on its own settings' frames, with its own
    draw (`protocol_seed`)."""
    emb = np.asarray(embeddings.numpy() if torch.is_tensor(embeddings) else embeddings, dtype=np.float32)
    frames = list(frames)
    settings = np.asarray(settings).astype(str)
    if len(frames) != len(settings) or len(frames) != len(emb):
        raise ValueError(f"evaluate_protocols: {len(frames)} frames, {len(settings)} settings, {len(emb)} embeddings")
    chosen = protocol_settings(settings, protocol, "test frames")
    out = {}
    for name, names in chosen.items():
        keep = np.isin(settings, names)
        sd = protocol_seed(seed, name)
        metrics, rankings, draw = evaluate(emb[keep], [f for f, k in zip(frames, keep) if k], settings[keep],
                                           protocol, sd, n_settings=len(names))
        rankings.insert(0, "protocol", name)
        out[name] = ProtocolResult(name, list(names), sd, metrics, rankings, draw)
    return out
