"""The NYU40 label table (ids, names, colours), as in Hypersim's `semantic_label_descs.csv`."""
from __future__ import annotations

import csv

import numpy as np

from monolib.paths import RESOURCES

UNLABELLED = -1
NUM_CLASSES = 40


def _load() -> tuple[list[str], np.ndarray]:
    with open(RESOURCES / "nyu40.csv", newline="") as f:
        rows = [{k.strip(): v.strip() for k, v in r.items()} for r in csv.DictReader(f)]
    ids = [int(r["semantic_id"]) for r in rows]
    if ids != list(range(1, NUM_CLASSES + 1)):
        raise ValueError(f"{RESOURCES / 'nyu40.csv'}: expected ids 1..40 in order, got {ids}")
    names = [r["semantic_name"] for r in rows]
    colours = np.array([[int(r[f"semantic_color_{c}"]) for c in "rgb"] for r in rows], dtype=np.uint8)
    return names, colours


NAMES, COLOURS = _load()
ID = {name: i + 1 for i, name in enumerate(NAMES)}  # name -> NYU40 id (1..40)


def name(label_id: int) -> str:
    """NYU40 name of an id in 1..40 ('unlabelled' for -1)."""
    return "unlabelled" if label_id == UNLABELLED else NAMES[int(label_id) - 1]


def colourize(semantic: np.ndarray) -> np.ndarray:
    """(H, W) NYU40 ids with -1 -> (H, W, 3) uint8 in the NYU40 palette, black where unlabelled."""
    palette = np.zeros((NUM_CLASSES + 2, 3), np.uint8)
    palette[1 : NUM_CLASSES + 1] = COLOURS
    idx = np.where((semantic >= 1) & (semantic <= NUM_CLASSES), semantic, 0).astype(np.intp)
    return palette[idx]
