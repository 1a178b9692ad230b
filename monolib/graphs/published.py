"""Scene graphs published with the original Monograph code (real Hypersim frames, GT depth and semantics).

A file ``ai_VVV_NNN_XX_graphs.pt`` is a `torch.save`d list of `Data` with `x` [N, 4] (NYU40 id, median R, G, B of
the HDR colour), `edge_index` [2, E] with only pairs i < j, `edge_attribute` [1, E] (lengths in metres, no `pos`)
and `y` = [setting digits 'VVVNNN', camera 'XX', frame 'IIII']. A study reads them from `graphs_root/train` and
`graphs_root/test`.

The reader is strict: anything else is one `PublishedGraphError` naming the file, the graph and what was expected.
That includes pairs with i > j, self-loops (i == i), a pair listed in both directions and a pair listed twice. The
release stores every unordered pair of distinct nodes exactly once, as i < j; a file that does not was written by
some other tool, and guessing its convention (directed edges? one length per direction, and which one wins?) would
silently change the graphs the encoder sees (the paper's encoder reads each pair once, i -> j, and the undirected
encoders both ways, so a pair listed twice would become a doubled edge), so the reader refuses it instead of
normalising it.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from torch_geometric.data import Data

from monolib.data import folds
from monolib.data.protocols import ProtocolDataError, protocol_settings
from monolib.io import DataFileError
from monolib.params import Study, resolve_path

FILE_RE = re.compile(r"^ai_(\d{3})_(\d{3})_(\d{2})_graphs\.pt$")


class PublishedGraphError(DataFileError, ValueError):
    """A published graph file or folder that is not in the release's format; the message names the file (a
    `DataFileError`, so the command prints it as one ``error:`` line and exits with status 2)."""


def _pair_problem(ei: torch.Tensor, n_nodes: int) -> str | None:
    """What is wrong with the pairs of an edge_index [2, E] of the release (None when every pair is i < j, once).
    Vectorised: a real release file holds about 100 graphs of up to some hundred pairs each."""
    i, j = ei[0], ei[1]
    key, rev = i * n_nodes + j, j * n_nodes + i
    both = (i != j) & torch.isin(rev, key)
    if both.any():
        c = int(both.nonzero()[0, 0])
        a, b = sorted((int(i[c]), int(j[c])))
        return f"pair ({a}, {b}) is listed in both directions; expected each pair once, as i < j"
    loop = i == j
    if loop.any():
        c = int(loop.nonzero()[0, 0])
        return f"self-loop ({int(i[c])}, {int(j[c])}) at edge {c}; expected pairs of two different nodes"
    wrong = i > j
    if wrong.any():
        c = int(wrong.nonzero()[0, 0])
        return f"pair ({int(i[c])}, {int(j[c])}) at edge {c} has i > j; expected pairs i < j only"
    uniq, counts = torch.unique(key, return_counts=True)
    if (counts > 1).any():
        k = int(uniq[counts > 1][0])
        return f"pair ({k // n_nodes}, {k % n_nodes}) is listed {int(counts.max())} times; expected each pair once"
    return None


def read_file(path: str | Path) -> list[Data]:
    """Graphs of one published file, converted to the cached complete-graph format (`pair_index`, `pair_len`).

    Raises `PublishedGraphError` (naming the file, the graph and what was expected) for a file that is not a list
    of graphs in the release's format: see the module docstring."""
    path = Path(path)
    m = FILE_RE.match(path.name)
    if not m:
        raise PublishedGraphError(f"{path}: expected a file named ai_VVV_NNN_XX_graphs.pt")
    if not path.is_file():
        raise PublishedGraphError(f"{path}: file not found")
    try:
        items = torch.load(path, weights_only=False)
    except Exception as exc:
        raise PublishedGraphError(f"{path}: not a readable torch file ({exc})") from exc
    if not isinstance(items, list):
        raise PublishedGraphError(f"{path}: expected a list of torch_geometric Data, got {type(items).__name__}")
    out = []
    for n, g in enumerate(items):
        def bad(msg: str):
            return PublishedGraphError(f"{path}: graph {n}: {msg}")

        if not isinstance(g, Data):
            raise bad(f"expected a torch_geometric Data, got {type(g).__name__}")
        for attr in ("x", "edge_index", "edge_attribute", "y"):
            if getattr(g, attr, None) is None:
                raise bad(f"no {attr!r} (expected x, edge_index, edge_attribute and y)")
            if attr != "y" and not torch.is_tensor(getattr(g, attr)):
                raise bad(f"{attr} is a {type(getattr(g, attr)).__name__}; expected a tensor")
        if g.x.dim() != 2 or g.x.shape[1] != 4:
            raise bad(f"x has shape {list(g.x.shape)}; expected [N, 4] (NYU40 id, R, G, B)")
        x = g.x.float()
        if g.edge_index.dim() != 2 or g.edge_index.shape[0] != 2:
            raise bad(f"edge_index has shape {list(g.edge_index.shape)}; expected [2, E]")
        ei = g.edge_index.long()
        length = g.edge_attribute.float().reshape(-1)
        if ei.shape[1] != length.shape[0]:
            raise bad(f"{ei.shape[1]} edges and {length.shape[0]} lengths; expected one length per edge")
        outside = (ei < 0) | (ei >= len(x))
        if outside.any():
            raise bad(f"edge_index refers to node {int(ei[outside][0])}; expected node indices 0..{len(x) - 1} "
                      f"({len(x)} nodes)")
        problem = _pair_problem(ei, len(x))
        if problem:
            raise bad(problem)
        y = list(g.y) if isinstance(g.y, (list, tuple)) else None
        if y is None or len(y) != 3:
            raise bad(f"y is {g.y!r}; expected [setting digits 'VVVNNN', camera 'XX', frame 'IIII']")
        setting_digits, cam, frame = (str(v) for v in y)
        if setting_digits != m.group(1) + m.group(2) or not cam.isdigit() or int(cam) != int(m.group(3)) \
                or not frame.isdigit():
            raise bad(f"y is {y!r}; expected ['{m.group(1)}{m.group(2)}', '{m.group(3)}', frame digits] as the file "
                      f"name says")
        setting = f"ai_{setting_digits[:3]}_{setting_digits[3:]}"
        out.append(Data(x=x, pair_index=ei, pair_len=length, setting=setting,
                        frame=f"{setting}/cam_{int(cam):02d}/{int(frame):04d}", num_nodes=len(x)))
    return out


def read_folder(folder: str | Path) -> list[Data]:
    """Every graph of the ``ai_VVV_NNN_XX_graphs.pt`` files of a folder, sorted by frame."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PublishedGraphError(f"{folder}: folder not found; expected a folder of published graph files "
                                  f"(ai_VVV_NNN_XX_graphs.pt)")
    files = sorted(p for p in folder.glob("ai_*_graphs.pt"))
    if not files:
        raise PublishedGraphError(f"{folder}: no published graph files; expected ai_VVV_NNN_XX_graphs.pt files")
    graphs = [g for p in files for g in read_file(p)]
    return sorted(graphs, key=lambda g: g.frame)


def _evenly(items: list, n: int) -> list:
    if len(items) <= n:
        return list(items)
    return [items[i] for i in np.round(np.linspace(0, len(items) - 1, n)).astype(int)]


def read_settings(root: Path, need_test: bool = True) -> dict[str, dict[str, list[Data]]]:
    """``{split: {setting: its graphs, by frame}}`` of the release's ``train/`` and ``test/`` folders. Without
    `need_test`, a missing ``test/`` is an empty split (a folder of training volumes alone, cross-validated by
    volume with ``protocol.release_split: false``)."""
    by_setting: dict[str, dict[str, list[Data]]] = {"train": {}, "test": {}}
    for split in by_setting:
        if split == "test" and not need_test and not (root / split).exists():
            continue
        for g in read_folder(root / split):
            by_setting[split].setdefault(g.setting, []).append(g)
    return by_setting


def select(study: Study) -> dict[str, list[Data]]:
    """Train / val / test graphs of a published-graphs study, selected as `selection.select_frames` does: the
    release's split, or fold `study.fold` of its volumes (`monolib.data.folds`), the training settings subsampled
    by `dataset.train_settings`."""
    root = resolve_path(study.graphs_root)
    pr = study.protocol
    if study.fold is None and not (root / "test").is_dir():
        raise PublishedGraphError(f"{root / 'test'}: folder not found; the release's own split needs its test/ "
                                  f"folder. A folder of training volumes alone is cross-validated by volume only: "
                                  f"protocol.split: volumes, protocol.release_split: false")
    by_split = read_settings(root, need_test=study.fold is None)
    graphs_of = {**by_split["train"], **by_split["test"]}
    train_names, test_all, label = folds.split_names(study, list(by_split["train"]), list(by_split["test"]))
    test_names = [s for s in test_all if len(graphs_of[s]) >= pr.frames]
    where = f"{root / 'test'} ({len(by_split['test'])} settings)" if study.fold is None else \
        f"{root} {label}: {len(test_all)} settings (protocol.folds: fewer folds give each more settings)"
    try:
        chosen = protocol_settings(test_names, pr, where)
    except ProtocolDataError as exc:
        raise PublishedGraphError(str(exc)) from None
    test = [g for s in sorted(set().union(*chosen.values())) for g in _evenly(graphs_of[s], pr.frames)]
    n_val = study.gcn.val_settings
    if len(train_names) <= n_val:
        where = root / "train" if study.fold is None else f"{root} {label}"
        raise PublishedGraphError(f"{where}: {len(train_names)} training settings, need more than "
                                  f"gcn.val_settings = {n_val}")
    per = study.dataset.train_frames_per_setting
    train = [g for s in train_names[: len(train_names) - n_val] for g in _evenly(graphs_of[s], per)]
    val = [g for s in train_names[len(train_names) - n_val :] for g in _evenly(graphs_of[s], per)]
    return {"train": train, "val": val, "test": test}
