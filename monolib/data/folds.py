"""Which settings a study trains and tests on, by name only: the data's own split (``protocol.split: release``) or
folds by volume (``volumes``), and the seeded subsample of the training settings (``dataset.train_settings``).
Read by frame selection (`monolib.data.selection`) and the published graphs (`monolib.graphs.published`).

Folds by volume: the volumes (``ai_VVV``, a setting's family) of the training and test splits together, sorted,
are permuted by the study's seed and dealt in turn into `protocol.folds` folds, so a volume is in exactly one fold
and no setting of a test volume is ever trained on. Fold k tests on its volumes' settings and trains on every other
fold's. A fold whose test settings cannot give the ``paper`` protocol its `protocol.settings` settings is one
`ProtocolDataError` naming the fold and its volumes (raised by `monolib.data.protocols.protocol_settings`): the
protocol is not shrunk to what the fold has, since a fold of fewer settings is an easier retrieval problem
(recall@1 of 16 places is not that of 10) and its numbers would not average with the others'.
"""
from __future__ import annotations

import numpy as np

from monolib.data.protocols import family
from monolib.errors import StudyError
from monolib.params import Study

FOLD_STREAM = 1  # the rng streams of the study's seed: the deal of volumes into folds ...
SUBSAMPLE_STREAM = 2  # ... and the subsample of the training settings


class FoldError(StudyError):
    """Fewer volumes than folds, or a fold asked of a study without folds (a study that cannot run: the command
    prints it as one error line)."""


def volume_folds(volumes, k: int, seed: int) -> list[list[str]]:
    """The volumes dealt into `k` folds: sorted, permuted by `seed`, dealt in turn (fold sizes differ by one at
    most); each fold's volumes sorted. Raises `FoldError` for fewer volumes than folds."""
    names = sorted(set(map(str, volumes)))
    if len(names) < k:
        raise FoldError(f"protocol.folds: {k} folds asked, the data holds {len(names)} volumes "
                        f"({', '.join(names) or 'none'}); expected at most one fold per volume")
    order = np.random.default_rng([int(seed), FOLD_STREAM]).permutation(len(names))
    return [sorted(names[i] for i in order[f::k]) for f in range(k)]


def fold_label(fold: int, k: int, volumes: list[str]) -> str:
    """How a fold is named in messages and reports: ``fold 2 of 5 (test volumes ai_003, ai_011)``."""
    return f"fold {fold} of {k} (test volumes {', '.join(volumes)})"


def split_names(study: Study, train: list[str], test: list[str]) -> tuple[list[str], list[str], str]:
    """``(training settings, test settings, what the test split is called)`` of the study's fold: the data's own
    split when `study.fold` is None; else fold `study.fold` of the volumes of both splits (`volume_folds`).
    The training settings are then subsampled (`subsample`)."""
    pr = study.protocol
    if study.fold is None:  # the data's own split (with folds by volume too: reported beside them)
        return subsample(study, sorted(train)), sorted(test), "test split"
    if pr.split != "volumes" or not 0 <= study.fold < pr.folds:
        raise FoldError(f"fold {study.fold}: expected none, or 0..folds - 1 with protocol.split: volumes "
                        f"(protocol.split: {pr.split}, protocol.folds: {pr.folds})")
    every = sorted(set(train) | set(test))
    volumes = volume_folds({family(s) for s in every}, pr.folds, study.seed)[study.fold]
    held = set(volumes)
    test_names = [s for s in every if family(s) in held]
    train_names = [s for s in every if family(s) not in held]
    return subsample(study, train_names), test_names, fold_label(study.fold, pr.folds, volumes)


def subsample(study: Study, names: list[str]) -> list[str]:
    """`dataset.train_settings` of the training settings `names`, drawn by the study's seed without replacement
    (all of them, sorted, when the key is not given or asks for as many as there are), sorted by name. The
    mini-Hypersim renders its training settings, so there the key is a size, not a subsample."""
    n = study.dataset.train_settings
    names = sorted(names)
    if study.dataset.source == "synth" and not study.graphs_root or n is None or n >= len(names):
        return names
    keep = np.random.default_rng([int(study.seed), SUBSAMPLE_STREAM]).choice(len(names), n, replace=False)
    return sorted(names[i] for i in keep)


def assignment(study: Study, settings) -> dict[str, int]:
    """``{volume: its fold}`` of the study's deal over `settings` (names of both splits): what the report lists."""
    folds = volume_folds({family(s) for s in settings}, study.protocol.folds, study.seed)
    return {v: f for f, vols in enumerate(folds) for v in vols}
