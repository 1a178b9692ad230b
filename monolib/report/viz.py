"""Plots of frames and cells shared by the notebooks (the notebooks themselves define nothing)."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use(matplotlib.get_backend() if "inline" in matplotlib.get_backend() else "agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from monolib.data import dataset, labels, selection
from monolib.io import save_figure


def frame_grid(frames, columns: tuple[str, ...] = ("rgb", "depth", "semantic"), size: float = 2.2):
    """One row per frame: RGB, planar depth (metres, colour bar) and semantics in the NYU40 palette."""
    fig, axes = plt.subplots(len(frames), len(columns), figsize=(size * 1.33 * len(columns), size * len(frames)),
                             squeeze=False)
    for r, f in enumerate(frames):
        for c, col in enumerate(columns):
            ax = axes[r, c]
            ax.set_xticks([]), ax.set_yticks([])
            if col == "rgb":
                ax.imshow(f.rgb)
                ax.set_ylabel(f"{f.setting}\n{f.scene} {f.index}", fontsize=7)
            elif col == "depth":
                im = ax.imshow(f.depth, cmap="magma_r")
                fig.colorbar(im, ax=ax, fraction=0.035, label="m")
            elif col == "semantic":
                ax.imshow(labels.colourize(f.semantic))
            if r == 0:
                ax.set_title({"rgb": "RGB (tonemapped)", "depth": "planar depth", "semantic": "NYU40 semantics"}[col],
                             fontsize=9)
    fig.tight_layout()
    return fig


def rgb_mosaic(frames, columns: int = 6, size: float = 1.6):
    """A grid of RGB frames (for docs/data.md)."""
    rows = int(np.ceil(len(frames) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(columns * size * 1.33, rows * size), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, f in zip(axes.ravel(), frames):
        ax.imshow(f.rgb)
        ax.set_title(f.setting, fontsize=6)
    fig.tight_layout()
    return fig


def training_curves(folder: str | Path):
    """Triplet loss (train, validation) and validation recall@1 of a cell's `history.csv`."""
    h = pd.read_csv(Path(folder) / "history.csv")
    fig, (a, b) = plt.subplots(1, 2, figsize=(8, 3))
    a.plot(h.epoch, h.train_loss, label="train")
    a.plot(h.epoch, h.val_loss, label="validation")
    a.set_xlabel("epoch"), a.set_ylabel("triplet loss"), a.legend()
    b.plot(h.epoch, 100 * h["val_recall@1"])
    b.set_xlabel("epoch"), b.set_ylabel("validation recall@1 (%)")
    fig.tight_layout()
    return fig


def save_dataset_mosaic(study, path, ds=None) -> None:
    """`frames.png`: one test frame of every test setting of a study (the grid of rooms of docs/data.md)."""
    ds = ds or dataset.open_dataset(study)
    sel = selection.select_frames(study, ds, study.gcn.val_settings)
    per = study.protocol.frames
    frames = [sel.test[i * per + per // 3] for i in range(len(sel.test) // per)]
    fig = rgb_mosaic(frames, columns=min(8, len(frames)))
    save_figure(fig, path)
    plt.close(fig)
