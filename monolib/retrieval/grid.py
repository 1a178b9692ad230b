"""The grid of a study: which cells it holds (methods x scenarios x thresholds x seeds, image methods x seeds).

Below the runner (`monolib.study.runner`), so that the report reads the cells of the grid and nothing else, and the
runner runs exactly those.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from monolib import methods, paths
from monolib.params import Study


@dataclass(frozen=True)
class CellSpec:
    method: str
    scenario: str
    threshold: float
    seed: int

    @property
    def name(self) -> str:
        return f"{self.method}/{self.scenario}__t{paths.threshold_tag(self.threshold)}__s{self.seed}"


def grid(study: Study) -> list[CellSpec]:
    """Every cell of the study: graph methods x scenarios x thresholds x seeds, image methods x seeds."""
    cells = []
    for m in study.methods + list(study.variants):
        if methods.kind(m, study) == "image":
            cells += [CellSpec(m, "rgb", math.inf, s) for s in study.seeds]
            continue
        v = study.variants.get(m)
        scenarios = (v.scenarios if v and v.scenarios else None) or [
            n for n, sc in study.scenarios.items() if sc.in_tables or m == "gcn"]
        for sc in scenarios:
            thresholds = (v.thresholds if v and v.thresholds else None) or study.scenarios[sc].thresholds or study.thresholds
            cells += [CellSpec(m, sc, t, s) for t in thresholds for s in study.seeds]
    return cells


def names(study: Study) -> set[str]:
    """The cell folder names of the grid (``method/scenario__t<t>__s<seed>``, relative to ``cells/``)."""
    return {c.name for c in grid(study)}
