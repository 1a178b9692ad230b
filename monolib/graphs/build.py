"""Back-projection and scene-graph construction (the paper's section 2, "Scene Graph Construction").

A frame becomes one node per NYU40 label present: position = per-axis median of the label's 3D points (camera
frame, metres), features = [NYU40 id, median R, G, B] (colour in 0..1), in ascending NYU40 id as the published
files hold them. Two nodes closer than the threshold are joined, with the length as edge attribute: once, i -> j for
i < j, as the original code joins them (`at_threshold`; `directed_by` points them along another node order), or in
both directions. Everything here is vectorised over pixels.

Two back-projections (`PROJECTIONS`, the study key `graphs.projection`):

- ``exact``: each scene's own camera (`Camera.rays`, Hypersim's `M_cam_from_uv`, tilt-shift included) with planar
  depth: true metres, x right, y up, z backward.
- ``monograph``: the original Monograph code's (`GenerateSceneGraph.py` and `config.py` of
  rupalsaxena/Monograph-Image-Retrieval): its own pinhole camera
  of 1024x768, f_w = 577.35 and f_h = 433.01 px (`MONOGRAPH_F_W`, `MONOGRAPH_F_H`), scaled to the frame's size
  (f times W / 1024 and H / 768), principal point (W // 2, H // 2), and the Euclidean distance `depth_meters` used
  as z: ``x = (j - W // 2) z / f_w``, ``y = (i - H // 2) z / f_h`` for pixel (row i, column j), axes as the
  original's (x right, y down, z forward). Its lengths come out 1.5-2 times the true ones; they are the space in
  which the paper's thresholds and the published graphs' lengths were measured. Planar depth (every depth source
  here) is turned back into the Euclidean distance with the scene's own camera first.
"""
from __future__ import annotations

import hashlib
import math
from typing import Optional

import numpy as np
import torch
from torch_geometric.data import Data

from monolib.data.hypersim import Camera
from monolib.params import NODE_ORDERS, PROJECTIONS

NODE_FEATURES = 4  # NYU40 id, median R, G, B
# The layout a graph encoder can read (`layout_graph`), in the camera frame (monocular: no world pose), axes made
# alike for both projections: right, up, forward. `FRAME_AXES[projection]` are the projection's (right, up,
# forward) directions: the original code's camera has y down and z forward, the exact one (Hypersim's) y up and z
# backward.
FRAME_AXES = {"monograph": ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
              "exact": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, -1.0))}
NODE_LAYOUT = 3  # a node's image column and row (right / forward, up / forward) and log of its forward distance
EDGE_LAYOUT = 3  # an edge's length, vertical offset (along the camera's up, m) and angle to the up direction (rad)
# the original code's camera (config.py): fov_x = 1.0471975803375244, fov_y = 2 atan(H tan(fov_x / 2) / W),
# f_h = 1000 tan(fov_y / 2), f_w = f_h W / H, at its fixed 1024x768
MONOGRAPH_FOV_X = 1.0471975803375244
MONOGRAPH_WIDTH, MONOGRAPH_HEIGHT = 1024, 768
MONOGRAPH_F_H = 1000.0 * math.tan(math.atan(MONOGRAPH_HEIGHT * math.tan(MONOGRAPH_FOV_X / 2) / MONOGRAPH_WIDTH))
MONOGRAPH_F_W = MONOGRAPH_F_H * MONOGRAPH_WIDTH / MONOGRAPH_HEIGHT


def monograph_rays(height: int, width: int) -> np.ndarray:
    """(H, W, 3) float64 multipliers of the original code's back-projection: point = ray * z, z the Euclidean
    distance (``((j - W // 2) / f_w, (i - H // 2) / f_h, 1)``, f of the 1024x768 camera scaled to W x H)."""
    f_w = MONOGRAPH_F_W * width / MONOGRAPH_WIDTH
    f_h = MONOGRAPH_F_H * height / MONOGRAPH_HEIGHT
    out = np.empty((height, width, 3), np.float64)
    out[..., 0] = ((np.arange(width) - width // 2) / f_w)[None, :]
    out[..., 1] = ((np.arange(height) - height // 2) / f_h)[:, None]
    out[..., 2] = 1.0
    return out


def check_projection(projection: str) -> str:
    if projection not in PROJECTIONS:
        raise ValueError(f"projection: expected one of {', '.join(PROJECTIONS)}, got {projection!r}")
    return projection


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


def grouped_median_u8(labels: np.ndarray, channels: np.ndarray, uniq: np.ndarray) -> np.ndarray:
    """Exact per-label median of uint8 channels (N, C) for the labels `uniq` (all present): (L, C) float64.

    One 256-bin histogram per label and channel (one `bincount` per channel), then the two middle ranks are read
    off the cumulative counts: no sort, no loop over labels or pixels. Even count = mean of the two middle values
    (as `numpy.median`).
    """
    base = np.asarray(labels, dtype=np.intp) * 256
    size = (int(uniq[-1]) + 1) * 256
    hist = np.stack([np.bincount(base + channels[:, c], minlength=size).reshape(-1, 256)
                     for c in range(channels.shape[1])], axis=1)[uniq]
    cum = np.cumsum(hist, axis=2)
    n = cum[:, :1, -1:]  # (L, 1, 1) pixels per label
    low = (cum <= (n - 1) // 2).sum(axis=2)
    high = (cum <= n // 2).sum(axis=2)
    return 0.5 * (low + high)


def frame_nodes(rgb: np.ndarray | None, depth: np.ndarray, semantic: np.ndarray,
                camera: Camera, projection: str = "exact") -> tuple[np.ndarray, np.ndarray, int]:
    """`scene_nodes` and the labelled pixels it left out for their depth (NaN, inf or <= 0), from one mask."""
    check_projection(projection)
    depth = np.asarray(depth, dtype=np.float32)
    semantic = np.asarray(semantic)
    if depth.shape != semantic.shape:
        raise ValueError(f"depth {depth.shape} and semantic {semantic.shape} differ in shape")
    if rgb is not None and rgb.shape[:2] != depth.shape:
        raise ValueError(f"rgb {rgb.shape} and depth {depth.shape} differ in size")
    labelled = (semantic >= 1).reshape(-1)
    with np.errstate(invalid="ignore"):
        valid = labelled & (np.isfinite(depth) & (depth > 0)).reshape(-1)
    x, pos = _nodes(rgb, depth, semantic, camera, valid, projection)
    return x, pos, int(np.count_nonzero(labelled)) - int(np.count_nonzero(valid))


def scene_nodes(rgb: np.ndarray | None, depth: np.ndarray, semantic: np.ndarray, camera: Camera,
                projection: str = "exact") -> tuple[np.ndarray, np.ndarray]:
    """Nodes of a frame: (x (L, 4) float32 [id, R, G, B in 0..1], pos (L, 3) float32 metres in `projection`).

    `depth`: planar metres (the scene's `camera`). Pixels with NaN, infinite or non-positive depth or label -1 are
    left out; no valid pixel gives L = 0. Positions are per-axis medians by one sort (`grouped_median`), uint8
    colours exact medians from histograms.
    """
    return frame_nodes(rgb, depth, semantic, camera, projection)[:2]


def _nodes(rgb, depth: np.ndarray, semantic: np.ndarray, camera: Camera, valid: np.ndarray,
           projection: str = "exact"):
    """The nodes of the pixels of `valid` (flat bool mask): `scene_nodes`."""
    if projection == "monograph":  # z = the Euclidean distance (from planar, with the scene's own rays)
        exact = camera.rays(*depth.shape)
        depth = depth.astype(np.float64) * (np.linalg.norm(exact, axis=-1) / -exact[..., 2])
        rays = monograph_rays(*depth.shape).reshape(-1, 3)
        scale = lambda d, r: d  # noqa: E731  (z = distance: no division by the ray's z)
    else:
        rays = camera.rays(*depth.shape).reshape(-1, 3)
        scale = lambda d, r: d / -r[:, 2]  # noqa: E731
    labels, d = semantic.reshape(-1), depth.reshape(-1)
    colours = None if rgb is None else rgb.reshape(-1, 3)
    if not valid.all():  # index only when needed: predicted frames are usually fully valid
        idx = np.flatnonzero(valid)
        if len(idx) == 0:
            return np.zeros((0, NODE_FEATURES), np.float32), np.zeros((0, 3), np.float32)
        rays, labels, d = rays[idx], labels[idx], d[idx]
        colours = None if colours is None else colours[idx]
    xyz = np.empty((3, len(d)), np.float64)  # C-ordered rows: the sort in grouped_median runs along each row
    xyz[:] = rays.T
    xyz *= scale(d, rays)
    uniq, pos = grouped_median(labels, xyz)
    if colours is None:
        colour = np.zeros((len(uniq), 3))
    elif colours.dtype == np.uint8:
        colour = grouped_median_u8(labels, colours, uniq) / 255.0
    else:
        colour = grouped_median(labels, np.ascontiguousarray(colours.T, dtype=np.float64))[1]
    x = np.concatenate([uniq[:, None].astype(np.float64), colour], axis=1).astype(np.float32)
    return x, pos.astype(np.float32)


def complete_graph(x, pos, setting: str = "", frame: str = "") -> Data:
    """A graph with every pair i < j and its length (from `pos`)."""
    x = torch.as_tensor(np.asarray(x), dtype=torch.float32).reshape(-1, NODE_FEATURES)
    pos = torch.as_tensor(np.asarray(pos), dtype=torch.float32).reshape(-1, 3)
    i, j = torch.triu_indices(len(x), len(x), offset=1)
    length = (pos[i].double() - pos[j].double()).norm(dim=1).float()
    return Data(x=x, pos=pos, pair_index=torch.stack([i, j]), pair_len=length, setting=setting, frame=frame,
                num_nodes=len(x))


def pair_mask(pair_len: torch.Tensor, threshold: float) -> torch.Tensor:
    """Which node pairs become edges at `threshold`: those closer than it (inf: all of them)."""
    return pair_len < threshold if math.isfinite(threshold) else torch.ones_like(pair_len, dtype=torch.bool)


def at_threshold(g: Data, threshold: float, both_directions: bool = True) -> Data:
    """The scene graph of `threshold`: edges for pairs closer than it (inf: all), in both directions by default, or
    once each, i -> j for i < j, as the original code held them (`both_directions=False`).

    `edge_attr` (E, 1) holds the lengths. Works for graphs built here and for published graphs alike.
    """
    keep = pair_mask(g.pair_len, threshold)
    ei, length = g.pair_index[:, keep], g.pair_len[keep]
    if both_directions:
        ei, length = torch.cat([ei, ei.flip(0)], dim=1), torch.cat([length, length])
    out = Data(x=g.x, edge_index=ei, edge_attr=length.unsqueeze(1), setting=g.setting, frame=g.frame,
               num_nodes=g.num_nodes)
    if getattr(g, "pos", None) is not None:
        out.pos = g.pos
    return out


def node_rank(g: Data, order: str) -> torch.Tensor:
    """(N,) each node's place in `order` (`monolib.params.NODE_ORDERS`): ``label`` the nodes as stored (ascending
    NYU40 id, as the published files hold them), ``reversed``, ``shuffled`` (a random order fixed per graph, drawn
    from its setting and frame, the same for every seed and epoch: a property of the input, not of the training),
    ``brightness`` (the sum of the node's R, G, B, darkest first) or ``distance`` (from the camera, nearest first;
    needs `pos`). Ties keep the stored order."""
    n = g.num_nodes
    if order == "label":
        return torch.arange(n)
    if order == "reversed":
        return torch.arange(n - 1, -1, -1)
    if order == "shuffled":
        seed = int.from_bytes(hashlib.sha256(f"node_order|{g.setting}|{g.frame}".encode()).digest()[:8], "little")
        return torch.as_tensor(np.random.default_rng(seed).permutation(n), dtype=torch.long)
    if order == "brightness":
        key = g.x[:, 1:NODE_FEATURES].double().sum(dim=1)
    elif order == "distance":
        if getattr(g, "pos", None) is None:
            raise ValueError(f"graph of frame {g.frame!r} ({g.setting}) has no node positions (pos): node_order: "
                             "distance needs them; published graphs hold only edge lengths")
        key = g.pos.double().norm(dim=1)
    else:
        raise ValueError(f"node_order: expected one of {', '.join(NODE_ORDERS)}, got {order!r}")
    rank = torch.empty(n, dtype=torch.long)
    rank[torch.argsort(key, stable=True)] = torch.arange(n)
    return rank


def directed_by(g: Data, order: str) -> Data:
    """`g` (a graph of `at_threshold` with each pair once) with every edge pointing from the node earlier in `order`
    to the later one (`node_rank`): GCNConv passes messages source -> target, so that a node hears only the nodes
    before it. Reordering the nodes this way is the same input to a GCN with max pooling as renumbering them."""
    if order == "label" or g.edge_index.shape[1] == 0:
        return g
    rank = node_rank(g, order)
    src, dst = g.edge_index
    swap = rank[src] > rank[dst]
    out = g.clone()
    out.edge_index = torch.stack([torch.where(swap, dst, src), torch.where(swap, src, dst)])
    return out


def layout_graph(g: Data, projection: Optional[str], node_layout: bool, edge_layout: bool) -> Data:
    """`g` (a graph of `at_threshold`) with its layout as features the encoder reads: with `node_layout` the
    columns of `node_layout_features` after x's four (x becomes (N, 4 + NODE_LAYOUT)); with `edge_layout` the
    edge attribute (length) followed by the vertical offset and the angle to up of each edge i -> j
    (`edge_layout_features`, (E, EDGE_LAYOUT)). Both need node positions (`pos`): published graphs hold only
    lengths, and asking for more of them is an error naming what is missing."""
    if not (node_layout or edge_layout):
        return g
    pos = getattr(g, "pos", None)
    if pos is None:
        raise ValueError(f"graph of frame {g.frame!r} ({g.setting}) has no node positions (pos): the layout "
                         "features (gcn.node_layout, gcn.edge_layout) need them; published graphs hold only "
                         "edge lengths")
    if projection not in FRAME_AXES:
        raise ValueError(f"projection: expected one of {', '.join(FRAME_AXES)}, got {projection!r}")
    out = g.clone()
    if node_layout:
        out.x = torch.cat([g.x, node_layout_features(pos, projection)], dim=1)
    if edge_layout:
        out.edge_attr = edge_layout_features(pos, g.edge_index, g.edge_attr, projection)
    return out


def node_layout_features(pos: torch.Tensor, projection: str) -> torch.Tensor:
    """(N, NODE_LAYOUT): where each node sits in the image (right / forward and up / forward, the tangents of its
    angles from the optical axis) and how far ahead (log of the forward distance in metres, at least 1 cm)."""
    axes = pos.new_tensor(FRAME_AXES[projection])  # (3, 3): right, up, forward
    ruf = pos @ axes.T
    forward = ruf[:, 2:].clamp_min(1e-2)
    return torch.cat([ruf[:, :2] / forward, forward.log()], dim=1)


def edge_layout_features(pos: torch.Tensor, edge_index: torch.Tensor, length: torch.Tensor,
                         projection: str) -> torch.Tensor:
    """(E, EDGE_LAYOUT) of edges i -> j: length (the graph's edge attribute, m), vertical offset of j above i
    along the camera's up (m), and the angle between the edge and the up direction (0: j straight above i, pi:
    straight below; pi / 2 for a zero-length edge)."""
    up = pos.new_tensor(FRAME_AXES[projection][1])
    length = length.reshape(-1, 1)
    rise = ((pos[edge_index[1]] - pos[edge_index[0]]) @ up).unsqueeze(1)
    cosine = torch.where(length > 0, rise / length.clamp_min(1e-9), torch.zeros_like(rise)).clamp(-1, 1)
    return torch.cat([length, rise, torch.arccos(cosine)], dim=1)


def build_scene_graph(rgb, depth, semantic, camera: Camera, threshold: float, projection: str = "exact") -> Data:
    """The scene graph of one frame: `x` = [NYU40 id, median R, G, B], `pos` = per-axis median (metres, camera
    frame of `projection`), `edge_index` both directions for every pair closer than `threshold` (inf joins all
    pairs), `edge_attr` = lengths (the encoders read it through `monolib.retrieval.gcn.encoder_graph`, which holds
    each pair once for the paper's encoder). A frame with no labelled pixel gives an empty graph (0 nodes)."""
    return at_threshold(complete_graph(*scene_nodes(rgb, depth, semantic, camera, projection)), threshold)
