"""The data stage: the study's dataset (a real Hypersim download, or the mini-Hypersim rendered by `synth`), opened
through one reader (`hypersim`), and the stage's key, part of every later stage's key."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

from monolib import versions
from monolib.data import synth
from monolib.data.hypersim import HypersimDataset
from monolib.io import sha256
from monolib.params import SYNTH_TRAIN_SETTINGS, Study, key_of


def ensure_dataset(study: Study, progress: bool = True) -> HypersimDataset:
    """The study's dataset, rendering the mini-Hypersim first when the study is synthetic (resumable, cached)."""
    if study.dataset.source == "synth":
        synth.render_dataset(study, study.dataset_root, progress=progress)
    return open_dataset(study)


def dataset_key(study: Study) -> str:
    """Cache key of the study's frames: the dataset parameters, the seed and, for a rendered mini-Hypersim, the
    version of the generator's code (`monolib.versions`). Part of every later stage's key."""
    spec = dataclasses.asdict(study.dataset)
    for where in ("root", "metadata_dir", "workers"):  # where the files are and how many processes read them
        spec.pop(where)
    if spec["base_train_settings"] is None:  # in the key only where a study sets it (it changes no other plan)
        spec.pop("base_train_settings")
    if spec["coplanar"] == "embree" or study.dataset.source != "synth":  # likewise: the keys of the studies rendered
        spec.pop("coplanar")  # before the choice existed, and of data this project does not render
    if study.dataset.source != "synth":
        # a real dataset's `train_settings` is a subsample of its training settings (None: all of them), under its
        # own name; `train_settings` holds the mini-Hypersim's default, as in the keys of every study without one
        subsample = spec.pop("train_settings")
        spec["train_settings"] = SYNTH_TRAIN_SETTINGS
        if subsample is not None:
            spec["train_subsample"] = subsample
    if study.dataset.source == "synth":
        return key_of({"dataset": spec, "seed": study.seed, "code": versions.code_version("dataset"),
                       "libraries": versions.library_versions("dataset")})
    return key_of({"dataset": spec, "seed": study.seed, "download": download_fingerprint(study)})


def download_fingerprint(study: Study) -> Optional[str]:
    """What a real download holds, cheaply: the sha256 of its split file (which names every frame of every
    setting) and the names of its setting folders. Files replaced in place under the same names are not seen:
    delete the study's runs folder after such a change."""
    root = study.dataset_root
    meta = study.metadata_dir or root
    split = Path(meta) / "metadata_images_split_scene_v1.csv"
    if not root.is_dir():
        return None
    names = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("ai_"))
    return key_of({"split": sha256(split) if split.is_file() else None, "settings": names})


def open_dataset(study: Study) -> HypersimDataset:
    return HypersimDataset(study.dataset_root, study.metadata_dir)
