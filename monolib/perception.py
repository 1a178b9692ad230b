"""The perception stage: train (or load) the segmentation net and the depth nets, evaluate them on the test split,
predict every selected frame, and cache everything; plus the readers the graph stage uses and the figures.

Cache layout (``<key>`` = `model_key`: the model's spec + the dataset parameters + the study seed, nothing else)::

    runs/<study>/models/<name>-<key>/model.pt         weights (+ mode/scale for depth)
    runs/<study>/models/<name>-<key>/history.json     per-epoch train loss and validation metrics, train seconds
    runs/<study>/models/<name>-<key>/metrics.json     test-split metrics, inference ms/frame
    runs/<study>/predictions/<name>-<key>/ai_VVV_NNN/images/scene_cam_XX_pred/frame.IIII.semantic_pred.hdf5
    runs/<study>/predictions/<name>-<key>/ai_VVV_NNN/images/scene_cam_XX_pred/frame.IIII.depth_planar_pred.hdf5
    runs/<study>/predictions/<name>-<key>/_complete.json   the frames predicted (the marker of a finished model)
    runs/<study>/perception/metrics.csv  and  figures_dir/perception.csv   the metrics table (long format)
"""
from __future__ import annotations

import dataclasses
import logging
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import pandas as pd

from monolib import io, paths
from monolib.params import Study, key_of, resolve_path

log = logging.getLogger(__name__)

SEM_SUFFIX = "semantic_pred.hdf5"
DEPTH_SUFFIX = "depth_planar_pred.hdf5"
COLUMNS = ["model", "role", "backbone", "task", "metric", "value", "train_seconds"]


# ---- names and paths -----------------------------------------------------------------------------------------

def _spec(study: Study, name: str):
    seg = study.perception.segmentation
    if name == seg.name:
        return seg, "segmentation"
    for d in study.perception.depth:
        if d.name == name:
            return d, "depth"
    raise KeyError(f"{study.path}: no perception model named {name!r} (have {study.model_names()})")


def model_key(study: Study, name: str) -> str:
    """Cache key of one model: its spec, the dataset parameters and the seed (GCN/scenario settings excluded)."""
    spec, task = _spec(study, name)
    return key_of({"task": task, "spec": dataclasses.asdict(spec), "dataset": dataclasses.asdict(study.dataset),
                   "seed": study.seed})


def model_tag(study: Study, name: str) -> str:
    return f"{name}-{model_key(study, name)}"


def model_dir(study: Study, name: str) -> Path:
    return study.data_dir / "models" / model_tag(study, name)


def predictions_dir(study: Study, name: str) -> Path:
    return study.data_dir / "predictions" / model_tag(study, name)


def prediction_path(study: Study, name: str, frame) -> Path:
    _, task = _spec(study, name)
    suffix = SEM_SUFFIX if task == "segmentation" else DEPTH_SUFFIX
    return (predictions_dir(study, name) / frame.setting / "images" / f"scene_{frame.scene}_pred"
            / f"frame.{frame.index:04d}.{suffix}")


# ---- readers for the graph stage ---------------------------------------------------------------------------

def _read_pred(path: Path, study: Study, name: str) -> np.ndarray:
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no cached prediction of model {name!r} for this frame; run the perception stage "
            f"(monolib.perception.run(load_study({study.name!r}))) first"
        )
    return io.read_h5(path)


def semantic_source(study: Study, name: str) -> Callable:
    """callable(frame) -> int16 (H, W) NYU40 ids: the frame's ground truth ('gt') or the model's cached prediction."""
    if name == "gt":
        def gt(frame):
            s = frame.semantic
            if s is None:
                raise io.DataFileError(f"{frame.files['semantic']}: file not found")
            return s.astype(np.int16)
        return gt
    _, task = _spec(study, name)
    if task != "segmentation":
        raise KeyError(f"{name!r} is a depth model, not a semantic source")

    def read(frame):
        return _read_pred(prediction_path(study, name, frame), study, name).astype(np.int16)
    return read


def depth_source(study: Study, name: str) -> Callable:
    """callable(frame) -> float32 (H, W) planar metres (NaN invalid): ground truth ('gt') or a cached prediction."""
    if name == "gt":
        return lambda frame: frame.depth.astype(np.float32)
    _, task = _spec(study, name)
    if task != "depth":
        raise KeyError(f"{name!r} is the segmentation model, not a depth source")

    def read(frame):
        return _read_pred(prediction_path(study, name, frame), study, name).astype(np.float32)
    return read


# ---- evaluation ----------------------------------------------------------------------------------------------

def evaluate_segmentation(pairs) -> dict:
    """pairs: iterable of (gt int16 (H, W), pred int16 (H, W)). Frames without labelled pixels add nothing."""
    from monolib.segmentation import confusion, scores
    from monolib.labels import NUM_CLASSES

    conf = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    for gt, pred in pairs:
        if gt is not None:
            conf += confusion(gt, pred)
    return scores(conf)


def evaluate_depth(pairs) -> dict:
    """pairs: iterable of (gt float32 (H, W), pred float32 (H, W)). Frames without valid depth are skipped."""
    from monolib.depth import depth_errors, summarise

    return summarise([depth_errors(pred, gt) for gt, pred in pairs])


# ---- the stage -----------------------------------------------------------------------------------------------

@contextmanager
def _threads(n: int):
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(max(1, int(n)))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _complete(study: Study, name: str, keys: list[str]) -> bool:
    marker = predictions_dir(study, name) / "_complete.json"
    if not marker.is_file() or not (model_dir(study, name) / "metrics.json").is_file():
        return False
    try:
        done = set(io.read_json(marker)["frames"])
    except (ValueError, KeyError, OSError):
        return False
    return set(keys) <= done


def _train_or_load(study: Study, name: str, sel, progress: bool):
    """(model, history): from model.pt when cached, else from `checkpoint:` or by training; saved either way."""
    from monolib import depth as dep
    from monolib import segmentation as seg

    spec, task = _spec(study, name)
    mod = seg if task == "segmentation" else dep
    mdir = model_dir(study, name)
    mpath, hpath = mdir / "model.pt", mdir / "history.json"
    if mpath.is_file() and hpath.is_file():
        return mod.load_model(spec, mpath), io.read_json(hpath), "loaded"
    t0 = time.perf_counter()
    if spec.checkpoint and task == "segmentation":
        model = seg.load_model(spec, resolve_path(spec.checkpoint, study.path))
        history = {"epochs": [], "source": str(spec.checkpoint), "train_seconds": 0.0}
    elif spec.checkpoint:
        model = dep.build_leres(spec.backbone)
        dep.load_adelai_checkpoint(model, resolve_path(spec.checkpoint, study.path))
        scale = dep.fit_scale(model, sel.train)
        history = {"epochs": [], "source": str(spec.checkpoint), "scale": scale,
                   "train_seconds": time.perf_counter() - t0}
    else:
        print(f"perception: training {name} ({task}, {spec.backbone}, {spec.epochs} epochs, "
              f"{len(sel.train)} train / {len(sel.val)} val frames at {spec.train_width}x{spec.train_height})")
        model, history = mod.train(spec, sel.train, sel.val, seed=study.seed, progress=progress)
    history["model"] = name
    mod.save_model(model, mpath)
    io.write_json(hpath, history)
    return model, history, "trained"


def _predict_all(study: Study, name: str, model, frames, progress: bool) -> tuple[int, float]:
    """Predict the frames whose prediction file is missing; returns (frames predicted, seconds of inference)."""
    from tqdm.auto import tqdm

    from monolib import depth as dep
    from monolib import segmentation as seg

    _, task = _spec(study, name)
    todo = [f for f in frames if not prediction_path(study, name, f).is_file()]
    bs = 8
    seconds = 0.0
    for i in tqdm(range(0, len(todo), bs), desc=f"predict {name}", disable=not progress, leave=False):
        chunk = todo[i : i + bs]
        rgb = np.stack([f.rgb for f in chunk])
        t0 = time.perf_counter()
        out = seg.predict(model, rgb, bs) if task == "segmentation" else dep.predict(model, rgb, bs)
        seconds += time.perf_counter() - t0
        for f, p in zip(chunk, out):
            io.write_h5(prediction_path(study, name, f), p.astype(np.int16 if task == "segmentation" else np.float32))
    return len(todo), seconds


def _evaluate(study: Study, name: str, test) -> dict:
    _, task = _spec(study, name)
    if task == "segmentation":
        read = semantic_source(study, name)
        return evaluate_segmentation((f.semantic, read(f)) for f in test)
    read = depth_source(study, name)
    return evaluate_depth((f.depth, read(f)) for f in test)


def _rows(study: Study, name: str) -> list[dict]:
    spec, task = _spec(study, name)
    mdir = model_dir(study, name)
    if not (mdir / "metrics.json").is_file():
        return []
    m = io.read_json(mdir / "metrics.json")
    role = "DeepLabV3" if task == "segmentation" else spec.role
    keys = ["pixel_accuracy", "miou"] if task == "segmentation" else ["abs_rel", "rmse", "delta1", "median_ratio"]
    keys += ["inference_ms_per_frame"]
    return [{"model": name, "role": role, "backbone": spec.backbone, "task": task, "metric": k,
             "value": m.get(k, float("nan")), "train_seconds": m.get("train_seconds", float("nan"))} for k in keys]


def metrics_table(study: Study) -> pd.DataFrame:
    """The metrics of every model of the study that has been evaluated (long format, `COLUMNS`)."""
    rows = [r for n in study.model_names() for r in _rows(study, n)]
    return pd.DataFrame(rows, columns=COLUMNS)


def _write_if_changed(path: Path, text: str) -> None:
    if path.is_file() and path.read_text() == text:
        return
    io.write_text(path, text)


def run(study: Study, progress: bool = True, only: Optional[list[str]] = None, dataset=None) -> pd.DataFrame:
    """Train/evaluate/predict each perception model unless cached; returns the metrics table.

    `only`: model names to run (default all). The table's ``attrs["status"]`` maps each model to
    'cached' (nothing done), or 'done' (something was trained, evaluated or predicted).
    """
    from monolib.dataset import ensure_dataset, select_frames

    names = only or study.model_names()
    status: dict[str, str] = {}
    ds = dataset
    sels: dict[int, object] = {}
    with _threads(study.perception.threads):
        for name in names:
            spec, task = _spec(study, name)
            tag = model_tag(study, name)
            if ds is None:
                ds = ensure_dataset(study, progress=progress)
            if spec.val_settings not in sels:
                sels[spec.val_settings] = select_frames(study, ds, spec.val_settings)
            sel = sels[spec.val_settings]
            frames = sel.all()
            keys = [f.key for f in frames]
            if _complete(study, name, keys):
                msg = f"perception: {tag} cached ({len(keys)} frames), nothing to do"
                print(msg)
                status[name] = "cached"
                continue
            model, history, how = _train_or_load(study, name, sel, progress)
            n_pred, secs = _predict_all(study, name, model, frames, progress)
            metrics = _evaluate(study, name, sel.test)
            old = model_dir(study, name) / "metrics.json"
            old_ms = io.read_json(old).get("inference_ms_per_frame") if old.is_file() else None
            metrics.update(
                train_seconds=float(history.get("train_seconds", float("nan"))),
                inference_ms_per_frame=(1000.0 * secs / n_pred) if n_pred else old_ms,
                test_frames=len(sel.test), frames=len(keys), key=model_key(study, name),
            )
            io.write_json(model_dir(study, name) / "metrics.json", metrics)
            io.write_json(predictions_dir(study, name) / "_complete.json", {"model": name, "frames": sorted(keys)})
            status[name] = "done"
            shown = {k: round(v, 4) for k, v in metrics.items() if k in ("pixel_accuracy", "miou", "abs_rel", "rmse", "delta1", "median_ratio")}
            print(f"perception: {tag} {how}, predicted {n_pred} frames, test {shown}")
    table = metrics_table(study)
    csv = table.to_csv(index=False, float_format="%.6g")
    _write_if_changed(study.data_dir / "perception" / "metrics.csv", csv)
    _write_if_changed(paths.figures_dir(study.name) / "perception.csv", csv)
    table.attrs["status"] = status
    return table


def wide(table: pd.DataFrame) -> pd.DataFrame:
    """The long metrics table as one row per model (for display)."""
    if table.empty:
        return table
    w = table.pivot_table(index=["model", "role", "backbone", "task"], columns="metric", values="value", sort=False)
    secs = table.groupby("model", sort=False)["train_seconds"].first()
    w = w.reset_index()
    w["train_seconds"] = w["model"].map(secs)
    return w


# ---- figures -------------------------------------------------------------------------------------------------

def _test_frames(study: Study, n: int, dataset=None):
    from monolib.dataset import open_dataset, select_frames

    ds = dataset or open_dataset(study)
    test = select_frames(study, ds, study.perception.segmentation.val_settings).test
    if not test:
        return []
    idx = np.round(np.linspace(0, len(test) - 1, min(n, len(test)))).astype(int)
    return [test[i] for i in idx]


def plot_training(study: Study, save: bool = True):
    """Per-epoch training loss and validation metric of every trained model -> `perception_training.png`."""
    import matplotlib.pyplot as plt

    names = [n for n in study.model_names() if (model_dir(study, n) / "history.json").is_file()]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for n in names:
        h = io.read_json(model_dir(study, n) / "history.json")
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
    srcs = [("ground truth", depth_source(study, "gt"))] + [(m, depth_source(study, m)) for m in models]
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
    """Figure 4: RGB, ground-truth semantics and the DeepLabV3 prediction in the NYU40 palette."""
    import matplotlib.pyplot as plt

    from monolib.labels import colourize

    frames = _test_frames(study, n, dataset)
    name = study.perception.segmentation.name
    pred = semantic_source(study, name)
    fig, axes = plt.subplots(len(frames), 3, figsize=(7.5, 1.9 * len(frames) + 0.3), squeeze=False)
    for r, f in enumerate(frames):
        for c, (img, title) in enumerate([(f.rgb, "RGB"), (colourize(f.semantic), "ground truth"),
                                          (colourize(pred(f)), f"DeepLabV3 ({name})")]):
            axes[r, c].imshow(img)
            axes[r, c].set_xticks([]), axes[r, c].set_yticks([])
            if r == 0:
                axes[r, c].set_title(title, fontsize=9)
    fig.tight_layout()
    if save:
        io.save_figure(fig, paths.figures_dir(study.name) / "fig4_semantics.png")
    return fig


def draw_figures(study: Study, dataset=None) -> None:
    """The stage's figures into `figures_dir`: training curves, Figure 3 (depth) and Figure 4 (semantics)."""
    import matplotlib.pyplot as plt

    plt.close(plot_training(study))
    plt.close(plot_depth_examples(study, dataset=dataset))
    plt.close(plot_semantic_examples(study, dataset=dataset))


def load_trained(study: Study, name: str):
    """The trained model `name` of the study from its cache (for the localizer); one clear error when missing."""
    from monolib import depth as dep
    from monolib import segmentation as seg

    spec, task = _spec(study, name)
    path = model_dir(study, name) / "model.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: model {name!r} is not trained; run `monolib perception {study.name}` first")
    model = (seg if task == "segmentation" else dep).load_model(spec, path)
    return model.eval()
