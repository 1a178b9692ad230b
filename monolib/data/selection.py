"""The frames a study uses: train / validation / test frames of its dataset, the test settings being those of the
protocols (`monolib.data.protocols`)."""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from monolib.data import folds
from monolib.data.hypersim import Frame, HypersimDataset
from monolib.data.protocols import protocol_settings
from monolib.params import Study

log = logging.getLogger(__name__)


def _evenly(items: list, n: int) -> list:
    if len(items) <= n:
        return list(items)
    idx = np.round(np.linspace(0, len(items) - 1, n)).astype(int)
    return [items[i] for i in idx]


@dataclass
class Selection:
    train: list[Frame]   # training split, minus the validation settings
    val: list[Frame]     # held-out training settings (model selection, early stopping)
    test: list[Frame]    # the protocol's test settings x frames

    def all(self) -> list[Frame]:
        return self.train + self.val + self.test


def select_frames(study: Study, ds: HypersimDataset, val_settings: int) -> Selection:
    """Deterministic frame selection.

    Test: the union of the protocols' settings (`monolib.data.protocols.protocol_settings`: ``paper``, one setting of
    each of `protocol.settings` families, and ``siblings``, both settings of `protocol.siblings` families), chosen
    among the test settings holding at least `protocol.frames` frames, sorted by name, `protocol.frames` frames each,
    evenly spread over the setting's scenes. Train: every training setting (`train_frames_per_setting` frames each,
    evenly spread); the last `val_settings` of them are validation. `dataset.max_settings` limits the training
    settings. Real Hypersim's 'val' partition counts as training data here (the study's validation is taken from it).
    With `protocol.split: volumes` the test settings are those of the study's fold and the training settings every
    other fold's; `dataset.train_settings` subsamples the training settings of real data (`monolib.data.folds`).
    """
    pr = study.protocol
    release_train = sorted(ds.settings("train") + ds.settings("val"))
    if study.dataset.max_settings:
        release_train = release_train[: study.dataset.max_settings]
    train_names, test_all, label = folds.split_names(study, release_train, ds.settings("test"))
    test_names = [s for s in test_all if len(ds.frames(s)) >= pr.frames]
    short = [f"{s} ({len(ds.frames(s))})" for s in test_all if len(ds.frames(s)) < pr.frames]
    where = (f"{ds.root} ({label}: {len(test_all)} settings"
             + (f"; with fewer than {pr.frames} frames: {', '.join(short[:8])}{' ...' if len(short) > 8 else ''})"
                if short else ")"))
    chosen = protocol_settings(test_names, pr, where)
    test_names = sorted(set().union(*chosen.values()))
    test = [f for s in test_names for f in _evenly(ds.frames(s), pr.frames)]
    if len(train_names) <= val_settings:
        raise ValueError(f"{ds.root} ({label}): {len(train_names)} training settings, need more than {val_settings} "
                         f"(validation)")
    per = study.dataset.train_frames_per_setting
    fit_names, val_names = (train_names[: len(train_names) - val_settings],
                            train_names[len(train_names) - val_settings :])
    train = [f for s in fit_names for f in _evenly(ds.frames(s), per)]
    val = [f for s in val_names for f in _evenly(ds.frames(s), per)]
    return Selection(train, val, test)
