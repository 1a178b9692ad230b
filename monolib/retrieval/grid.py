"""The grid of a study: which cells it holds (methods x scenarios x thresholds x seeds, image methods x seeds).

Below the runner (`monolib.study.runner`), so that the report reads the cells of the grid and nothing else, and the
runner runs exactly those.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

from monolib import methods, paths
from monolib.params import Study


@dataclass(frozen=True)
class CellSpec:
    method: str
    scenario: str
    threshold: float
    seed: int
    fold: Optional[int] = None  # with `protocol.split: volumes`: the fold tested (`Study.at_fold`)

    @property
    def name(self) -> str:
        return f"{self.method}/{paths.cell_name(self.scenario, self.threshold, self.seed, self.fold)}"


def grid(study: Study) -> list[CellSpec]:
    """Every cell of the study: graph methods x scenarios x thresholds x seeds (and the `more_seeds` of some of
    them, right after the study's seeds of the same cell), image methods x seeds; each of them once per fold with
    `protocol.split: volumes` (fold-major, so that a fold's cells run in a row)."""
    cells = []
    for m in study.methods + list(study.variants):
        if methods.kind(m, study) == "image":
            cells += [CellSpec(m, "rgb", math.inf, s) for s in study.seeds]
            continue
        for sc, thresholds in study.cell_thresholds(m).items():
            for t in thresholds:
                more = [s for e in study.more_seeds if e.method == m and sc in e.scenarios and t in e.thresholds
                        for s in e.seeds]
                cells += [CellSpec(m, sc, t, s) for s in study.seeds + more]
    return [replace(c, fold=f) for f in study.folds() for c in cells]


def names(study: Study) -> set[str]:
    """The cell folder names of the grid's release split (``method/scenario__t<t>__s<seed>``, relative to
    ``cells/``): what the report's tables read. The folds' cells (``...__f<fold>``) have their own tables
    (`monolib.report.folds`)."""
    return {c.name for c in grid(study) if c.fold is None}
