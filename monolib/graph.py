"""Back-projection and scene-graph construction (the paper's section 2, "Scene Graph Construction").

A frame becomes one node per NYU40 label present: position = per-axis median of the label's 3D points (camera
frame, metres), features = [NYU40 id, median R, G, B] (colour in 0..1). Two nodes closer than the threshold are
joined in both directions, with the length as edge attribute. Everything here is vectorised over pixels.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch_geometric.data import Data

from monolib.hypersim import Camera

NODE_FEATURES = 4  # NYU40 id, median R, G, B


def grouped_median(labels: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-label median of each row of `values` (C, N): returns (unique labels (L,), medians (L, C)).

    `labels` (N,) are small non-negative integers (NYU40 ids). Each value is mapped into [rank, rank + 0.5] of its
    label, so one sort of all rows at once groups by label and orders by value: no loop over labels or pixels.
    Median of an even count = mean of the two middle values (as `numpy.median`).
    """
    labels = np.asarray(labels, dtype=np.int64)
    values = np.atleast_2d(np.asarray(values, dtype=np.float64))
    if len(labels) == 0:
        return np.zeros(0, np.int64), np.zeros((0, values.shape[0]))
    counts = np.bincount(labels)
    uniq = np.flatnonzero(counts)
    n = counts[uniq]
    rank_of = np.zeros(len(counts), np.float64)
    rank_of[uniq] = np.arange(len(uniq))
    low = values.min(axis=1, keepdims=True)
    span = values.max(axis=1, keepdims=True) - low
    span[span == 0] = 1.0
    scale = 0.5 / span
    keys = values - low
    keys *= scale
    keys += rank_of[labels]
    keys.sort(axis=1)
    starts = np.cumsum(n) - n
    mid = 0.5 * (keys[:, starts + (n - 1) // 2] + keys[:, starts + n // 2]) - np.arange(len(uniq))
    return uniq, (mid / scale + low).T


def scene_nodes(rgb: np.ndarray | None, depth: np.ndarray, semantic: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Nodes of a frame: (x (L, 4) float32 [id, R, G, B in 0..1], pos (L, 3) float32 metres, camera frame).

    Pixels with NaN / non-positive depth or label -1 are left out; no valid pixel gives L = 0.
    """
    depth = np.asarray(depth, dtype=np.float32)
    semantic = np.asarray(semantic)
    if depth.shape != semantic.shape:
        raise ValueError(f"depth {depth.shape} and semantic {semantic.shape} differ in shape")
    if rgb is not None and rgb.shape[:2] != depth.shape:
        raise ValueError(f"rgb {rgb.shape} and depth {depth.shape} differ in size")
    with np.errstate(invalid="ignore"):
        valid = (depth > 0) & (semantic >= 1)  # NaN > 0 is False
    idx = np.flatnonzero(valid)
    if len(idx) == 0:
        return np.zeros((0, NODE_FEATURES), np.float32), np.zeros((0, 3), np.float32)
    rays = camera.rays(*depth.shape).reshape(-1, 3)[idx]
    z = depth.reshape(-1)[idx] / -rays[:, 2]
    values = np.empty((6, len(idx)), np.float64)
    values[:3] = rays.T * z
    if rgb is None:
        values[3:] = 0.0
    else:
        values[3:] = rgb.reshape(-1, 3)[idx].T
        if rgb.dtype == np.uint8:
            values[3:] /= 255.0
    uniq, med = grouped_median(semantic.reshape(-1)[idx], values)
    x = np.concatenate([uniq[:, None].astype(np.float64), med[:, 3:6]], axis=1).astype(np.float32)
    return x, med[:, :3].astype(np.float32)


def edges_within(pos: torch.Tensor, threshold: float, both_directions: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Edges between every pair of nodes closer than `threshold` metres (inf: all pairs).

    Returns (edge_index (2, E) long, edge_attr (E, 1) float lengths); with `both_directions` every pair appears
    as (i, j) and (j, i), else only i < j (the published code's convention).
    """
    n = pos.shape[0]
    if n < 2:
        return torch.zeros((2, 0), dtype=torch.long), torch.zeros((0, 1), dtype=torch.float32)
    d = torch.cdist(pos.double(), pos.double())
    keep = d < threshold if math.isfinite(threshold) else torch.ones_like(d, dtype=torch.bool)
    keep &= ~torch.eye(n, dtype=torch.bool)
    if not both_directions:
        keep &= torch.ones(n, n, dtype=torch.bool).triu(1)
    i, j = keep.nonzero(as_tuple=True)
    return torch.stack([i, j]), d[i, j].float().unsqueeze(1)


def make_graph(x, pos, threshold: float, **meta) -> Data:
    """A `Data` from nodes (x, pos) with the edges of `threshold`; `meta` (setting, frame, ...) is attached."""
    x = torch.as_tensor(np.asarray(x), dtype=torch.float32).reshape(-1, NODE_FEATURES)
    pos = torch.as_tensor(np.asarray(pos), dtype=torch.float32).reshape(-1, 3)
    edge_index, edge_attr = edges_within(pos, float(threshold))
    return Data(x=x, pos=pos, edge_index=edge_index, edge_attr=edge_attr, **meta)


def build_scene_graph(rgb, depth, semantic, camera: Camera, threshold: float) -> Data:
    """The paper's scene graph of one frame: `x` = [NYU40 id, median R, G, B], `pos` = per-axis median (metres,
    camera frame), `edge_index` both directions for every pair closer than `threshold` (inf joins all pairs),
    `edge_attr` = lengths. A frame with no labelled pixel gives an empty graph (0 nodes)."""
    x, pos = scene_nodes(rgb, depth, semantic, camera)
    return make_graph(x, pos, threshold)


def with_threshold(graph: Data, threshold: float) -> Data:
    """The same nodes with the edges of another threshold (from `pos`)."""
    g = graph.clone()
    g.edge_index, g.edge_attr = edges_within(g.pos, float(threshold))
    return g
