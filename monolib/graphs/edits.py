"""Edits of built scene graphs, one property of the data each: what `monolib.study.data_edits` changes to find
which property of the data sets what the edges cost an encoder.

Every edit takes the graphs of one study (as `monolib.graphs.scenegraphs.load` gives them: x = [NYU40 id, R, G, B, ...],
the complete pairs `pair_index` / `pair_len`, `pos` when built here) and returns new graphs; the inputs are never
changed. Node colours are the graphs' own (HDR medians in both legs of the study, the published graphs' space).

- `relight`: each label's colours scaled by a factor of its own (`light_factors`: the factors that give one set of
  graphs another's light, a label's median brightness relative to the wall's);
- `expose`: every colour scaled by one factor (the overall exposure, the wall's median);
- `thin_label`: a label's nodes removed from a seeded share of the graphs that hold it (how often it appears);
- `drop_nodes`: a seeded share of each graph's nodes removed, the wall and floor kept (nodes per graph).
"""
from __future__ import annotations

import hashlib
from typing import Mapping

import numpy as np
import torch
from torch_geometric.data import Data

WALL = 1  # NYU40 ids: the reference of `light_ratios`, and what `drop_nodes` keeps with the floor
FLOOR = 2


def brightness(x: torch.Tensor) -> torch.Tensor:
    """(N,) a node's brightness: the mean of its R, G, B (columns 1-3 of x)."""
    return x[:, 1:4].mean(dim=1)


def label_brightness(graphs: list[Data]) -> dict[int, float]:
    """``{NYU40 id: median brightness of its nodes}`` over every node of `graphs`."""
    xs = [g.x for g in graphs if g.num_nodes]
    if not xs:
        return {}
    x = torch.cat(xs)
    labels, lum = x[:, 0].long().numpy(), brightness(x).numpy()
    return {int(lab): float(np.median(lum[labels == lab])) for lab in np.unique(labels)}


def light_ratios(graphs: list[Data]) -> dict[int, float]:
    """``{NYU40 id: its median brightness / the wall's}``: how bright each kind of object is against the walls of
    the same graphs (a lamp, a window, a lit ceiling). Empty when no wall is there to compare with."""
    med = label_brightness(graphs)
    wall = med.get(WALL)
    if not wall or wall <= 0:
        return {}
    return {lab: v / wall for lab, v in med.items()}


def light_factors(source: Mapping[int, float], target: Mapping[int, float]) -> dict[int, float]:
    """The factor per label that moves graphs of `source`'s light ratios to `target`'s (labels in both, with a
    positive ratio on both sides; any other label keeps its colours: factor 1)."""
    return {lab: float(target[lab] / r) for lab, r in source.items() if r > 0 and target.get(lab, 0) > 0}


def _with_x(g: Data, x: torch.Tensor) -> Data:
    out = g.clone()
    out.x = x
    return out


def relight(graphs: list[Data], factors: Mapping[int, float]) -> list[Data]:
    """Each node's R, G, B times its label's factor (1 for a label not in `factors`)."""
    if not factors:
        return [g.clone() for g in graphs]
    top = max(max(factors), 0) + 1
    table = torch.ones(top + 1)
    for lab, f in factors.items():
        if lab >= 0:
            table[lab] = f
    out = []
    for g in graphs:
        labels = g.x[:, 0].long().clamp(0, top)
        scale = table.to(g.x.device, g.x.dtype)[labels].unsqueeze(1)
        out.append(_with_x(g, torch.cat([g.x[:, :1], g.x[:, 1:4] * scale, g.x[:, 4:]], dim=1)))
    return out


def expose(graphs: list[Data], factor: float) -> list[Data]:
    """Every node's R, G, B times `factor`."""
    return [_with_x(g, torch.cat([g.x[:, :1], g.x[:, 1:4] * factor, g.x[:, 4:]], dim=1)) for g in graphs]


def keep_nodes(g: Data, keep: torch.Tensor) -> Data:
    """`g` with the nodes of the boolean mask `keep` only, in their order, and the pairs between them."""
    index = torch.full((g.num_nodes,), -1, dtype=torch.long, device=keep.device)
    index[keep] = torch.arange(int(keep.sum()), device=keep.device)
    pairs = keep[g.pair_index[0]] & keep[g.pair_index[1]]
    out = Data(x=g.x[keep], pair_index=index[g.pair_index[:, pairs]], pair_len=g.pair_len[pairs],
               setting=g.setting, frame=g.frame, num_nodes=int(keep.sum()))
    if getattr(g, "pos", None) is not None:
        out.pos = g.pos[keep]
    return out


def _frame_draw(seed: int, frame: str, salt: str) -> np.random.Generator:
    """A generator drawn from the seed, the frame and the edit: the same frame gets the same draw in every run,
    whatever the order of the graphs."""
    digest = hashlib.sha256(f"{seed}/{salt}/{frame}".encode()).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def thin_label(graphs: list[Data], label: int, share: float, seed: int) -> list[Data]:
    """`label`'s nodes removed from each graph that holds it with probability 1 - `share`: of the graphs that held
    it, about `share` still do (drawn per frame: `_frame_draw`)."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"thin_label: share {share}, expected a number in [0, 1]")
    out = []
    for g in graphs:
        has = g.x[:, 0].long() == label
        if bool(has.any()) and _frame_draw(seed, g.frame, f"thin{label}").random() >= share:
            out.append(keep_nodes(g, ~has))
        else:
            out.append(g.clone())
    return out


def drop_nodes(graphs: list[Data], share: float, seed: int) -> list[Data]:
    """Each node but the walls and floors removed with probability `share` (drawn per frame)."""
    if not 0.0 <= share < 1.0:
        raise ValueError(f"drop_nodes: share {share}, expected a number in [0, 1)")
    out = []
    for g in graphs:
        labels = g.x[:, 0].long()
        draw = torch.as_tensor(_frame_draw(seed, g.frame, "drop").random(g.num_nodes), device=g.x.device)
        keep = (draw >= share) | (labels == WALL) | (labels == FLOOR)
        out.append(keep_nodes(g, keep))
    return out


def label_share(graphs: list[Data], label: int) -> float:
    """The share of graphs with a node of `label`."""
    return float(np.mean([bool((g.x[:, 0].long() == label).any()) for g in graphs])) if graphs else float("nan")


def light_effects(graphs: list[Data], rounds: int = 50) -> tuple[dict[str, float], dict[int, float]]:
    """The log brightness of every node split into a setting's light level and a label's (an additive fit, by
    alternating means): ``({setting: its effect}, {NYU40 id: its effect})``, the settings' centred on their mean.
    How much the light differs between places is the spread of the first; between kinds of object, the second's."""
    xs = [g.x for g in graphs if g.num_nodes]
    if not xs:
        return {}, {}
    settings = np.concatenate([[g.setting] * g.num_nodes for g in graphs if g.num_nodes])
    x = torch.cat(xs)
    labels = x[:, 0].long().numpy()
    y = np.log(brightness(x).clamp_min(1e-6).double().numpy())
    s_codes, s_names = np.unique(settings, return_inverse=True)[1], np.unique(settings)
    l_names, l_codes = np.unique(labels, return_inverse=True)
    s_eff, l_eff = np.zeros(len(s_names)), np.zeros(len(l_names))
    s_n, l_n = np.bincount(s_codes, minlength=len(s_names)), np.bincount(l_codes, minlength=len(l_names))
    for _ in range(rounds):
        l_eff = np.bincount(l_codes, y - s_eff[s_codes], len(l_names)) / l_n
        s_eff = np.bincount(s_codes, y - l_eff[l_codes], len(s_names)) / s_n
    s_eff -= s_eff.mean()
    return ({str(s): float(e) for s, e in zip(s_names, s_eff)},
            {int(lab): float(e) for lab, e in zip(l_names, l_eff)})


def spread_setting_light(graphs: list[Data], factor: float) -> list[Data]:
    """Each setting's light level (`light_effects`, fitted on `graphs`) moved `factor` times as far from the mean
    of the settings: every node of setting s times exp((factor - 1) e_s). factor 0 gives every place one light
    level, 1 the graphs as they are, 2 twice the spread (sd of the log brightness) between places."""
    effects, _ = light_effects(graphs)
    out = []
    for g in graphs:
        scale = float(np.exp((factor - 1.0) * effects.get(g.setting, 0.0)))
        out.append(_with_x(g, torch.cat([g.x[:, :1], g.x[:, 1:4] * scale, g.x[:, 4:]], dim=1)))
    return out
