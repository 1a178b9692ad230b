"""Which cells of the grid are the same computation as another cell, so that the runner copies that cell's results
instead of running them again (`same_graphs`): a threshold whose scene graphs equal a smaller one's, or a cell whose
encoder reads exactly what a cell of an earlier scenario reads (`monolib.retrieval.cell.copy_cell` does the copy).
"""
from __future__ import annotations

import hashlib

from monolib import methods
from monolib.graphs import scenegraphs
from monolib.params import Study
from monolib.retrieval import gcn
from monolib.retrieval.grid import CellSpec


def same_graphs(study: Study, cells: list[CellSpec],
                scenario_keys: dict[str, str] | None = None) -> dict[str, CellSpec]:
    """{cell name: source cell} for the graph cells that are the same computation as another cell of the same
    method, seed and fold (same inputs, encoder and seed), so that the runner copies the source's results:

    - within a scenario, a threshold whose scene graphs equal those of a smaller one: no pair of nodes, in any
      frame of any split, has a length between the two (edges only grow with the threshold, so equal edge totals
      mean equal graphs). With predicted depth every pair is often closer than 5 m, and 5, 10 and inf give one
      graph set;
    - across scenarios, a cell whose encoder reads exactly what a cell of an earlier scenario reads at the same
      threshold (`monolib.retrieval.gcn.input_fingerprint`): two depth networks with the same semantics give the
      paper's GCN the same graphs without edges (0 m) and with every pair joined (inf), as it reads no length.

    `scenario_keys`: the graph stage's keys, when the caller holds them."""
    import torch

    groups: dict[tuple, list[CellSpec]] = {}
    for c in cells:
        if methods.kind(c.method, study) == "graph":
            groups.setdefault((c.method, c.scenario, c.seed, c.fold), []).append(c)
    loaded: dict[tuple, dict] = {}

    def graphs_of(scenario: str, fold) -> dict:
        if (scenario, fold) not in loaded:
            loaded[scenario, fold] = scenegraphs.load(study.at_fold(fold), scenario,
                                                      key=(scenario_keys or {}).get(scenario) if fold is None else None)
        return loaded[scenario, fold]

    lengths: dict[tuple, torch.Tensor] = {}
    out = {}
    for (_, scenario, _, fold), group in groups.items():
        if (scenario, fold) not in lengths:
            lengths[scenario, fold] = torch.cat([g.pair_len for split in graphs_of(scenario, fold).values()
                                                 for g in split] + [torch.zeros(0)])
        by_threshold = {float(c.threshold): c for c in group}
        for t, source in scenegraphs.identical_thresholds(lengths[scenario, fold], by_threshold).items():
            out[by_threshold[t].name] = by_threshold[source]
    out.update(_same_inputs(study, [c for c in cells if c.name not in out and c.scenario in study.scenarios
                                    and methods.kind(c.method, study) == "graph"], graphs_of))
    return out


def _same_inputs(study: Study, cells: list[CellSpec], graphs_of) -> dict[str, CellSpec]:
    """The cross-scenario part of `same_graphs`: {cell name: the cell of the earliest scenario (study order) whose
    encoder reads the same inputs at the same threshold}. Only scenarios whose node features are identical are
    compared edge by edge."""
    order = {name: i for i, name in enumerate(study.scenarios)}
    nodes: dict[tuple, str] = {}

    def node_digest(scenario: str, fold) -> str:
        if (scenario, fold) not in nodes:
            h = hashlib.sha256()
            for split, graphs in sorted(graphs_of(scenario, fold).items()):
                for g in graphs:
                    h.update(f"{split}|{g.setting}|{g.frame}|".encode())
                    h.update(g.x.numpy().tobytes())
            nodes[scenario, fold] = h.hexdigest()
        return nodes[scenario, fold]

    candidates: dict[tuple, list[CellSpec]] = {}
    for c in cells:
        candidates.setdefault((c.method, float(c.threshold), c.seed, c.fold), []).append(c)
    digests: dict[tuple, str] = {}
    out = {}
    for (method, threshold, _, fold), group in candidates.items():
        if len({c.scenario for c in group}) < 2:
            continue
        spec = study.gcn_spec(method)
        first: dict[str, CellSpec] = {}
        for c in sorted(group, key=lambda c: order[c.scenario]):
            if sum(node_digest(o.scenario, fold) == node_digest(c.scenario, fold) for o in group) < 2:
                continue
            k = (c.scenario, fold, threshold, method)
            if k not in digests:
                graphs = graphs_of(c.scenario, fold)
                digests[k] = gcn.input_fingerprint([g for split in sorted(graphs) for g in graphs[split]], threshold,
                                                   spec, study.projection(c.scenario))
            if digests[k] in first:
                out[c.name] = first[digests[k]]
            else:
                first[digests[k]] = c
    return out
