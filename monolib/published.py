"""Scene graphs published with the original Monograph code (real Hypersim frames, GT depth and semantics).

A file ``ai_VVV_NNN_XX_graphs.pt`` is a `torch.save`d list of `Data` with `x` [N, 4] (NYU40 id, median R, G, B of
the HDR colour), `edge_index` [2, E] with only pairs i < j, `edge_attribute` [1, E] (lengths in metres, no `pos`)
and `y` = [setting digits 'VVVNNN', camera 'XX', frame 'IIII']. A study reads them from `graphs_root/train` and
`graphs_root/test`.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Data

from monolib.params import Study, resolve_path

FILE_RE = re.compile(r"^ai_(\d{3})_(\d{3})_(\d{2})_graphs\.pt$")


def read_file(path: str | Path) -> list[Data]:
    """Graphs of one published file, converted to the cached complete-graph format (`pair_index`, `pair_len`)."""
    path = Path(path)
    if not FILE_RE.match(path.name):
        raise ValueError(f"{path}: expected a file named ai_VVV_NNN_XX_graphs.pt")
    try:
        items = torch.load(path, weights_only=False)
    except Exception as exc:
        raise ValueError(f"{path}: not a readable torch file ({exc})") from exc
    if not isinstance(items, list):
        raise ValueError(f"{path}: expected a list of torch_geometric Data, got {type(items).__name__}")
    out = []
    for n, g in enumerate(items):
        for attr in ("x", "edge_index", "edge_attribute", "y"):
            if getattr(g, attr, None) is None:
                raise ValueError(f"{path}: graph {n} has no {attr!r}")
        x = g.x.float().reshape(-1, 4)
        ei = g.edge_index.long()
        length = g.edge_attribute.float().reshape(-1)
        if ei.shape[1] != length.shape[0]:
            raise ValueError(f"{path}: graph {n} has {ei.shape[1]} edges and {length.shape[0]} lengths")
        lo, hi = torch.minimum(ei[0], ei[1]), torch.maximum(ei[0], ei[1])  # i < j whatever the file says
        keep = lo != hi
        setting_digits, cam, frame = (str(v) for v in g.y)
        setting = f"ai_{setting_digits[:3]}_{setting_digits[3:]}"
        out.append(Data(x=x, pair_index=torch.stack([lo[keep], hi[keep]]), pair_len=length[keep], setting=setting,
                        frame=f"{setting}/cam_{int(cam):02d}/{int(frame):04d}", num_nodes=len(x)))
    return out


def read_folder(folder: str | Path) -> list[Data]:
    folder = Path(folder)
    files = sorted(p for p in folder.glob("ai_*_graphs.pt"))
    if not files:
        raise ValueError(f"{folder}: no published graph files (ai_VVV_NNN_XX_graphs.pt)")
    graphs = [g for p in files for g in read_file(p)]
    return sorted(graphs, key=lambda g: g.frame)


def _evenly(items: list, n: int) -> list:
    if len(items) <= n:
        return list(items)
    return [items[i] for i in np.round(np.linspace(0, len(items) - 1, n)).astype(int)]


def select(study: Study) -> dict[str, list[Data]]:
    """Train / val / test graphs of a published-graphs study, selected as `dataset.select_frames` does."""
    root = resolve_path(study.graphs_root, study.path)
    pr = study.protocol
    by_setting: dict[str, dict[str, list[Data]]] = {}
    for split in ("train", "test"):
        for g in read_folder(root / split):
            by_setting.setdefault(split, {}).setdefault(g.setting, []).append(g)
    test_names = [s for s in sorted(by_setting["test"]) if len(by_setting["test"][s]) >= pr.frames]
    from monolib.retrieval import protocol_settings

    chosen = protocol_settings(test_names, pr, f"{root / 'test'} ({len(by_setting['test'])} settings)")
    test = [g for s in sorted(set().union(*chosen.values())) for g in _evenly(by_setting["test"][s], pr.frames)]
    names = sorted(by_setting["train"])
    n_val = study.gcn.val_settings
    if len(names) <= n_val:
        raise ValueError(f"{root / 'train'}: {len(names)} settings, need more than gcn.val_settings = {n_val}")
    per = study.dataset.train_frames_per_setting
    train = [g for s in names[: len(names) - n_val] for g in _evenly(by_setting["train"][s], per)]
    val = [g for s in names[len(names) - n_val :] for g in _evenly(by_setting["train"][s], per)]
    return {"train": train, "val": val, "test": test}
