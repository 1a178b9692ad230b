"""The perception stage's figures and its metrics table for display: the training curves, the paper's Figure 3
(depth) and Figure 4 (semantics) from the stage's cached models and predictions (`monolib.perception.predictions`),
into the study's `figures_dir`. They compute nothing the stage caches, so an edited figure recomputes nothing."""
from __future__ import annotations

import numpy as np
import pandas as pd

from monolib import io, paths
from monolib.data import labels
from monolib.data.dataset import open_dataset
from monolib.data.selection import select_frames
from monolib.params import Study
from monolib.perception import predictions


def wide(table: pd.DataFrame) -> pd.DataFrame:
    """The long metrics table as one row per model (for display)."""
    if table.empty:
        return table
    w = table.pivot_table(index=["model", "role", "backbone", "task"], columns="metric", values="value", sort=False)
    secs = table.groupby("model", sort=False)["train_seconds"].first()
    w = w.reset_index()
    w["train_seconds"] = w["model"].map(secs)
    return w


def _test_frames(study: Study, n: int, dataset=None):
    ds = dataset or open_dataset(study)
    test = select_frames(study, ds, study.perception.segmentation.val_settings).test
    if not test:
        return []
    idx = np.round(np.linspace(0, len(test) - 1, min(n, len(test)))).astype(int)
    return [test[i] for i in idx]


def plot_training(study: Study, save: bool = True):
    """Per-epoch training loss and validation metric of every trained model -> `perception_training.png`."""
    import matplotlib.pyplot as plt

    histories = {n: io.load_cached(predictions.model_dir(study, n) / "history.json", io.read_json_dict,
                                   f"training history of {n}")
                 for n in study.model_names()}
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for n, h in histories.items():
        if h is None:
            continue
        ep = [r["epoch"] for r in h.get("epochs", [])]
        if not ep:
            continue
        axes[0].plot(ep, [r["train_loss"] for r in h["epochs"]], marker="o", label=n)
        key = "val_miou" if "val_miou" in h["epochs"][0] else "val_delta1"
        axes[1].plot(ep, [r.get(key, np.nan) for r in h["epochs"]], marker="o",
                     label=f"{n} ({'mIoU' if key == 'val_miou' else 'delta<1.25'})")
    axes[0].set(title="training loss", xlabel="epoch")
    axes[1].set(title="validation metric", xlabel="epoch", ylim=(0, 1))
    for a in axes:
        if a.lines:
            a.legend(fontsize=8)
    fig.tight_layout()
    if save:
        io.save_figure(fig, paths.figures_dir(study.name) / "perception_training.png")
    return fig


def plot_depth_examples(study: Study, n: int = 3, save: bool = True, dataset=None):
    """Figure 3: RGB, ground truth beside each depth model, in metres (shared range per row) and normalised 0..1."""
    import matplotlib.pyplot as plt

    frames = _test_frames(study, n, dataset)
    models = [d.name for d in study.perception.depth]
    srcs = [("ground truth", predictions.depth_source(study, "gt"))] + [(m, predictions.depth_source(study, m))
                                                                        for m in models]
    ncol = 1 + 2 * len(srcs)
    fig, axes = plt.subplots(len(frames), ncol, figsize=(1.9 * ncol, 1.6 * len(frames) + 0.4), squeeze=False)
    for r, f in enumerate(frames):
        maps = [s(f) for _, s in srcs]
        finite = np.concatenate([m[np.isfinite(m)] for m in maps] + [np.array([0.0, 1.0])])
        vmax = float(np.percentile(finite, 99))
        axes[r, 0].imshow(f.rgb)
        axes[r, 0].set_title("RGB" if r == 0 else "", fontsize=8)
        for c, ((label, _), m) in enumerate(zip(srcs, maps)):
            ax = axes[r, 1 + c]
            ax.imshow(m, cmap="magma_r", vmin=0, vmax=vmax)
            if r == 0:
                ax.set_title(f"{label} (m)", fontsize=8)
            ok = np.isfinite(m)
            norm = np.full(m.shape, np.nan, np.float32)
            if ok.any():
                lo, hi = float(m[ok].min()), float(m[ok].max())
                norm[ok] = (m[ok] - lo) / max(hi - lo, 1e-6)
            ax2 = axes[r, 1 + len(srcs) + c]
            ax2.imshow(norm, cmap="magma_r", vmin=0, vmax=1)
            if r == 0:
                ax2.set_title(f"{label} (0..1)", fontsize=8)
        axes[r, 0].set_ylabel(f"{f.setting}\ncolour 0-{vmax:.1f} m", fontsize=7)
    for a in axes.ravel():
        a.set_xticks([]), a.set_yticks([])
    if save:
        io.save_figure(fig, paths.figures_dir(study.name) / "fig3_depth.png")
    return fig


def plot_semantic_examples(study: Study, n: int = 3, save: bool = True, dataset=None):
    """Figure 4: RGB, ground-truth semantics and the DeepLabV3 prediction in the NYU40 palette, with a legend of
    the NYU40 classes present in the shown frames (ground truth or prediction; black: unlabelled)."""
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    frames = _test_frames(study, n, dataset)
    name = study.perception.segmentation.name
    pred = predictions.semantic_source(study, name)
    fig, axes = plt.subplots(len(frames), 3, figsize=(7.5, 1.9 * len(frames) + 0.3), squeeze=False)
    present: set[int] = set()
    unlabelled = False
    for r, f in enumerate(frames):
        gt, pr = f.semantic, pred(f)
        for semantic in (gt, pr):
            ids = np.unique(semantic)
            known = (ids >= 1) & (ids <= labels.NUM_CLASSES)
            present |= {int(i) for i in ids[known]}
            unlabelled |= bool((~known).any())
        for c, (img, title) in enumerate([(f.rgb, "RGB"), (labels.colourize(gt), "ground truth"),
                                          (labels.colourize(pr), f"DeepLabV3 ({name})")]):
            axes[r, c].imshow(img)
            axes[r, c].set_xticks([]), axes[r, c].set_yticks([])
            if r == 0:
                axes[r, c].set_title(title, fontsize=9)
    fig.tight_layout()
    handles = [Patch(facecolor=labels.COLOURS[i - 1] / 255.0, edgecolor="0.5", linewidth=0.4, label=labels.name(i))
               for i in sorted(present)]
    if unlabelled:
        handles.append(Patch(facecolor="black", edgecolor="0.5", linewidth=0.4, label="unlabelled"))
    if handles:
        fig.legend(handles=handles, loc="center left", bbox_to_anchor=(1.0, 0.5), fontsize=7, frameon=False,
                   title="NYU40 classes shown", title_fontsize=8, ncol=1 + (len(handles) - 1) // 20)
    if save:
        io.save_figure(fig, paths.figures_dir(study.name) / "fig4_semantics.png")
    return fig


def draw_figures(study: Study, dataset=None) -> None:
    """The stage's figures into `figures_dir`: training curves, Figure 3 (depth) and Figure 4 (semantics)."""
    import matplotlib.pyplot as plt

    plt.close(plot_training(study))
    plt.close(plot_depth_examples(study, dataset=dataset))
    plt.close(plot_semantic_examples(study, dataset=dataset))
