"""The frames a study uses: open (or render) its dataset and select train / validation / test frames."""
from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from monolib.hypersim import Frame, HypersimDataset
from monolib.params import Study

log = logging.getLogger(__name__)


def ensure_dataset(study: Study, progress: bool = True) -> HypersimDataset:
    """The study's dataset, rendering the mini-Hypersim first when the study is synthetic (resumable, cached)."""
    if study.dataset.source == "synth":
        from monolib import synth

        synth.render_dataset(study, study.dataset_root, progress=progress)
    return open_dataset(study)


def dataset_key(study: Study) -> str:
    """Cache key of the study's frames: the dataset parameters, the seed and, for a rendered mini-Hypersim, the
    version of the generator's code (`monolib.versions`). Part of every later stage's key."""
    from monolib.params import key_of
    from monolib.versions import code_version, library_versions

    spec = dataclasses.asdict(study.dataset)
    for where in ("root", "metadata_dir", "workers"):  # where the files are and how many processes read them
        spec.pop(where)
    if study.dataset.source == "synth":
        return key_of({"dataset": spec, "seed": study.seed, "code": code_version("dataset"),
                       "libraries": library_versions("dataset")})
    return key_of({"dataset": spec, "seed": study.seed, "download": download_fingerprint(study)})


def download_fingerprint(study: Study) -> Optional[str]:
    """What a real download holds, cheaply: the sha256 of its split file (which names every frame of every
    setting) and the names of its setting folders. Files replaced in place under the same names are not seen:
    delete the study's runs folder after such a change."""
    from monolib.io import sha256

    root = study.dataset_root
    meta = study.metadata_dir or root
    split = Path(meta) / "metadata_images_split_scene_v1.csv"
    if not root.is_dir():
        return None
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("ai_"))
    return key_of_text([sha256(split) if split.is_file() else "", *names])


def key_of_text(parts: list[str]) -> str:
    import hashlib

    return hashlib.sha256("\n".join(parts).encode()).hexdigest()[:16]


def open_dataset(study: Study) -> HypersimDataset:
    return HypersimDataset(study.dataset_root, study.metadata_dir)


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

    Test: the union of the protocols' settings (`monolib.retrieval.protocol_settings`: ``paper``, one setting of
    each of `protocol.settings` families, and ``siblings``, both settings of `protocol.siblings` families), chosen
    among the test settings holding at least `protocol.frames` frames, sorted by name, `protocol.frames` frames each,
    evenly spread over the setting's scenes. Train: every training setting (`train_frames_per_setting` frames each,
    evenly spread); the last `val_settings` of them are validation. `dataset.max_settings` limits the training
    settings. Real Hypersim's 'val' partition counts as training data here (the study's validation is taken from it).
    """
    from monolib.protocols import protocol_settings

    pr = study.protocol
    test_names = [s for s in ds.settings("test") if len(ds.frames(s)) >= pr.frames]
    short = [f"{s} ({len(ds.frames(s))})" for s in ds.settings("test") if len(ds.frames(s)) < pr.frames]
    where = (f"{ds.root} (test split: {len(ds.settings('test'))} settings"
             + (f"; with fewer than {pr.frames} frames: {', '.join(short[:8])}{' ...' if len(short) > 8 else ''})"
                if short else ")"))
    chosen = protocol_settings(test_names, pr, where)
    test_names = sorted(set().union(*chosen.values()))
    test = [f for s in test_names for f in _evenly(ds.frames(s), pr.frames)]
    train_names = ds.settings("train") + ds.settings("val")
    train_names = sorted(train_names)
    if study.dataset.max_settings:
        train_names = train_names[: study.dataset.max_settings]
    if len(train_names) <= val_settings:
        raise ValueError(f"{ds.root}: {len(train_names)} training settings, need more than {val_settings} (validation)")
    per = study.dataset.train_frames_per_setting
    fit_names, val_names = train_names[: len(train_names) - val_settings], train_names[len(train_names) - val_settings :]
    train = [f for s in fit_names for f in _evenly(ds.frames(s), per)]
    val = [f for s in val_names for f in _evenly(ds.frames(s), per)]
    return Selection(train, val, test)
