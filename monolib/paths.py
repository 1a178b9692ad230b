"""Every path of the project comes from here; nothing depends on the current working directory."""
from __future__ import annotations

import math
import os
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent
ROOT = PACKAGE.parent
PARAMS = ROOT / "params"
NOTEBOOKS = ROOT / "notebooks"
FIGURES = Path(os.environ.get("MONOLIB_FIGURES", ROOT / "figures"))
RUNS = Path(os.environ.get("MONOLIB_RUNS", ROOT / "runs"))
RESOURCES = PACKAGE / "resources"  # the shipped tables and weights
# params/ files that are not studies: the claims per study (monolib.report.claims) and the data edits' own study
# file (monolib.study.data_edits)
NOT_STUDIES = ("claims.yaml", "data_edits.yaml")


def study_files() -> list[Path]:
    """params/*.yaml that are study files (`monolib.params.load_study`), in name order."""
    return [p for p in sorted(PARAMS.glob("*.yaml")) if p.name not in NOT_STUDIES]


def study_dir(study_name: str) -> Path:
    """`runs/<study>/`: datasets, checkpoints, predictions, graphs, cells and executed notebooks of one study."""
    return RUNS / study_name


def threshold_tag(threshold: float) -> str:
    """Folder-safe name of a threshold: 0 (no edges) -> '0', 1.0 -> '1', 2.5 -> '2.5', 2.5000001 -> '2.5000001',
    inf -> 'inf' (12 significant digits: two thresholds that share a name are refused when the study loads)."""
    t = float(threshold) + 0.0  # -0.0 -> 0.0
    if t == float("inf"):
        return "inf"
    return f"{t:.12g}"


def threshold_json(threshold: float) -> float | str:
    """A threshold as cell.json stores it: JSON has no infinity, so inf -> 'inf' (`float()` reads both back)."""
    t = float(threshold) + 0.0  # -0.0 -> 0.0
    return t if math.isfinite(t) else "inf"


def cell_stem(scenario: str, threshold: float) -> str:
    """The part of a cell's folder name that its seeds share: ``<scenario>__t<threshold>``."""
    return f"{scenario}__t{threshold_tag(threshold)}"


def cell_name(scenario: str, threshold: float, seed: int, fold: int | None = None) -> str:
    """A cell's folder name: ``<scenario>__t<threshold>__s<seed>``, and ``__f<fold>`` for a fold of a study with
    folds by volume (a study without folds keeps the names it always had)."""
    name = f"{cell_stem(scenario, threshold)}__s{int(seed)}"
    return name if fold is None else f"{name}__f{int(fold)}"


def cell_dir(study_name: str, method: str, scenario: str, threshold: float, seed: int, fold: int | None = None) -> Path:
    """`runs/<study>/cells/<method>/<cell_name>/`."""
    return study_dir(study_name) / "cells" / method / cell_name(scenario, threshold, seed, fold)


DEFAULT_STUDY = "quick"
# the studies whose results are committed, and where (every other study writes into runs/<study>/figures/)
COMMITTED_FIGURES = {"quick": "", "ablations": "ablations", "direction": "direction", "colour": "colour",
                     "perception_long": "perception_long", "scratch": "scratch", "real": "real",
                     "real_full": "real_full", "paper_scale": "paper_scale", "quick_96x40": "quick_96x40",
                     "real_96x40": "real_96x40"}


def figures_dir(study_name: str) -> Path:
    """Where a study's tables and figures go: `figures/` for the default (quick) study, `figures/<name>/` for the
    other committed studies (`COMMITTED_FIGURES`), else `runs/<study>/figures/`."""
    if study_name in COMMITTED_FIGURES:
        return FIGURES / COMMITTED_FIGURES[study_name] if COMMITTED_FIGURES[study_name] else FIGURES
    return study_dir(study_name) / "figures"
