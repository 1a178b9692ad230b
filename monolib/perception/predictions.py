"""The perception stage: train (or load) the segmentation net and the depth nets, evaluate them on the test split,
predict every selected frame, and cache everything; plus the readers the graph stage uses. The stage's figures:
`monolib.report.perception_figures`.

Cache layout (``<key>`` = `model_key`: the model's spec + the dataset parameters + the study seed, nothing else)::

    runs/<study>/models/<name>-<key>/model.pt         weights (+ mode/scale for depth)
    runs/<study>/models/<name>-<key>/history.json     per-epoch train loss and validation metrics, train seconds
    runs/<study>/models/<name>-<key>/metrics.json     test-split metrics, inference ms/frame
    runs/<study>/predictions/<name>-<key>/ai_VVV_NNN/images/scene_cam_XX_pred/frame.IIII.semantic_pred.hdf5
    runs/<study>/predictions/<name>-<key>/ai_VVV_NNN/images/scene_cam_XX_pred/frame.IIII.depth_planar_pred.hdf5
    runs/<study>/predictions/<name>-<key>/_complete.json   the frames predicted (the marker of a finished model)
    runs/<study>/perception/metrics_<study>.csv  and  figures_dir/perception.csv   the metrics table (long format)
"""
from __future__ import annotations

import dataclasses
import functools
import logging
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import pandas as pd

from monolib import device as devices, io, paths, versions
from monolib.data.labels import NUM_CLASSES
from monolib.data.selection import select_frames
from monolib.data.dataset import dataset_key as data_key, ensure_dataset
from monolib.params import Study, StudyError, key_of, resolve_path
from monolib.perception import depth as dep, manifests, segmentation as seg, weights
from monolib.perception.images import FrameRgb
from monolib.perception.depth import depth_errors, summarise
from monolib.perception.segmentation import confusion, scores
from monolib.progress import tqdm

log = logging.getLogger(__name__)

SEM_SUFFIX = "semantic_pred.hdf5"
DEPTH_SUFFIX = "depth_planar_pred.hdf5"
COLUMNS = ["model", "role", "backbone", "task", "metric", "value", "train_seconds"]


# ---- names and paths -----------------------------------------------------------------------------------------

def _spec(study: Study, name: str):
    segmentation = study.perception.segmentation
    if name == segmentation.name:
        return segmentation, "segmentation"
    for d in study.perception.depth:
        if d.name == name:
            return d, "depth"
    raise KeyError(f"{study.path}: no perception model named {name!r} (have {study.model_names()})")


def model_key(study: Study, name: str, dataset_key: Optional[str] = None) -> str:
    """Cache key of one model and its predictions: its spec (not its name or role, which are labels), the
    content of its shipped weights or checkpoint file (not their paths), the dataset's key, the seed, the device
    and deterministic mode, whether the predictions are made in float16 (`perception.amp` on CUDA; never on the
    CPU), the stage's thread count and `predict_batch` (on the CPU a prediction depends on both in its last bits),
    the version of the perception code and of its libraries (`monolib.versions`). Not part of it: GCN and
    scenario settings, the loader workers (which change no prediction). `dataset_key`: the data stage's key, when
    the caller holds it; computed here otherwise."""
    spec, task = _spec(study, name)
    shipped = checkpoint = None
    if spec.weights:  # the shipped file's identity (its manifest's sha256, checked when it is loaded)
        shipped = manifests.read_manifest(resolve_path(spec.weights))["sha256"]
    if spec.checkpoint:  # an outside file: its content, not its path
        checkpoint = _file_sha256(resolve_path(spec.checkpoint))
    fields = dataclasses.asdict(spec)
    for label in ("name", "role", "weights", "checkpoint"):  # names and paths: the files' content is below
        fields.pop(label, None)
    return key_of({"task": task, "spec": fields,
                   "dataset": dataset_key if dataset_key is not None else data_key(study),
                   "seed": study.seed, "device": devices.device().type, "deterministic": study.deterministic,
                   "amp": study.perception.amp and devices.device().type == "cuda",
                   "threads": study.perception.threads, "predict_batch": study.perception.predict_batch,
                   "code": versions.code_version("perception"), "libraries": versions.library_versions("perception"),
                   "weights": shipped, "checkpoint": checkpoint})


@functools.lru_cache(maxsize=32)
def _file_sha256_at(path: str, size: int, mtime_ns: int) -> str:
    return io.sha256(path)


def _file_sha256(path: Path) -> Optional[str]:
    """sha256 of a file (hashed once per size and modification time); None when it is absent (the stage says so)."""
    path = Path(path)
    if not path.is_file():
        return None
    st = path.stat()
    return _file_sha256_at(str(path), st.st_size, st.st_mtime_ns)


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

class PredictionsMissing(io.DataFileError):
    """A model's predictions, which a scenario needs, are missing or unreadable (the message names the command)."""


def missing_predictions(study: Study, name: str, cause, unreadable: Optional[Path] = None) -> PredictionsMissing:
    """The error of a missing or unreadable prediction of model `name`; an `unreadable` prediction file is removed
    so that the perception stage predicts that frame again."""
    if unreadable is not None:
        unreadable.unlink(missing_ok=True)
    return PredictionsMissing(
        f"model {name!r} of study {study.name!r}: missing or unreadable prediction ({cause}). The graphs of a scenario "
        f"with predicted depth or semantics need every prediction; make them with `monolib perception "
        f"{study.path or study.name}` (or `monolib study {study.path or study.name}`, which runs perception first)")


def check_predictions(study: Study, name: str, frames) -> None:
    """`PredictionsMissing` unless model `name` has a prediction file for every frame (`_complete`; checked before a
    graph build, which then reads each file and reports one that is cut short)."""
    if _complete(study, name, frames):
        return
    if not (model_dir(study, name) / "metrics.json").is_file():
        raise missing_predictions(study, name, f"{model_dir(study, name)}: the model has not been trained or evaluated")
    lacking = [f for f in frames if not prediction_path(study, name, f).is_file()]
    if lacking:
        raise missing_predictions(study, name, f"{prediction_path(study, name, lacking[0])}: no such file "
                                               f"({len(lacking)} of {len(frames)} frames lack a prediction)")


def _read_pred(path: Path, study: Study, name: str) -> np.ndarray:
    try:
        return io.read_h5(path)
    except io.DataFileError as exc:
        raise missing_predictions(study, name, exc, unreadable=path if path.is_file() else None) from None


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
    conf = np.zeros((NUM_CLASSES, NUM_CLASSES), np.int64)
    for gt, pred in pairs:
        if gt is not None:
            conf += confusion(gt, pred)
    return scores(conf)


# A depth network whose predictions hold more than this share of non-finite pixels (NaN, inf) is an error, never a
# cached model: those pixels would leave the depth metrics and the scene graphs silently (a network predicting NaN
# for 90% of the pixels would report a good abs_rel on the other 10%). A sound network predicts none.
MAX_NONFINITE_SHARE = 0.001


class NonFiniteDepth(io.DataFileError):
    """A depth network predicts non-finite depth for more than `MAX_NONFINITE_SHARE` of the pixels."""


def evaluate_depth(pairs) -> dict:
    """pairs: iterable of (gt float32 (H, W), pred float32 (H, W)). Frames without valid depth are skipped by the
    error metrics; ``nonfinite_share`` counts the predicted pixels that are NaN or inf over every frame."""
    rows, nonfinite, total = [], 0, 0
    for gt, pred in pairs:
        rows.append(depth_errors(pred, gt))
        nonfinite += int(np.count_nonzero(~np.isfinite(pred)))
        total += int(np.size(pred))
    out = summarise(rows)
    out["nonfinite_share"] = nonfinite / total if total else 0.0
    return out


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


def _complete(study: Study, name: str, frames) -> bool:
    """Trained, evaluated and every frame predicted: the marker and the metrics are readable and every prediction
    file is present (one removed as unreadable by the graph stage makes the model incomplete again)."""
    marker = io.load_cached(predictions_dir(study, name) / "_complete.json",
                            lambda p: io.read_json_dict(p, ("frames",)), "perception marker")
    metrics = io.load_cached(model_dir(study, name) / "metrics.json", io.read_json_dict, "perception metrics")
    if marker is None or metrics is None:
        return False
    return {f.key for f in frames} <= set(marker["frames"]) and all(
        prediction_path(study, name, f).is_file() for f in frames)


def _train_or_load(study: Study, name: str, sel, progress: bool):
    """(model, history): from model.pt when cached, else from `checkpoint:` or by training; saved either way."""
    spec, task = _spec(study, name)
    mod = seg if task == "segmentation" else dep
    mdir = model_dir(study, name)
    mpath, hpath = mdir / "model.pt", mdir / "history.json"
    history = io.load_cached(hpath, lambda p: io.read_json_dict(p, ("epochs",)), f"training history of {name}")
    model = io.load_cached(mpath, lambda p: mod.load_model(spec, p), f"weights of {name}") if history else None
    if model is not None:
        return model, history, "loaded"
    t0 = time.perf_counter()
    if spec.weights:  # the project's zoo: inference only
        model = weights.load(spec, task, spec.weights)
        manifest = manifests.read_manifest(resolve_path(spec.weights))
        history = {"epochs": [], "source": str(spec.weights), "sha256": manifest["sha256"],
                   "pretrain_seconds": manifest.get("train_seconds"), "train_seconds": 0.0}
        print(f"perception: {name} from the zoo ({spec.weights}, trained {manifest.get('train_seconds')} s on "
              f"{manifest.get('device')})", flush=True)
    elif spec.checkpoint and task == "segmentation":
        model = seg.load_model(spec, resolve_path(spec.checkpoint))
        history = {"epochs": [], "source": str(spec.checkpoint), "train_seconds": 0.0}
    elif spec.checkpoint:
        model = dep.build_leres(spec.backbone)
        dep.load_adelai_checkpoint(model, resolve_path(spec.checkpoint))
        scale = dep.fit_scale(model, sel.train)
        history = {"epochs": [], "source": str(spec.checkpoint), "scale": scale,
                   "train_seconds": time.perf_counter() - t0}
    else:
        print(f"perception: training {name} ({task}, {spec.backbone}, {spec.epochs} epochs, "
              f"{len(sel.train)} train / {len(sel.val)} val frames at {spec.train_width}x{spec.train_height})")
        model, history = mod.train(spec, sel.train, sel.val, seed=study.seed, progress=progress,
                                   deterministic=study.deterministic)
    history["model"] = name
    mod.save_model(model, mpath)
    io.write_json(hpath, history)
    return model, history, "trained"


def predict_frames(model, task: str, frames, spec, write: Callable, progress: bool = False,
                   desc: str = "predict", rgb: Optional[FrameRgb] = None) -> float:
    """Predict `frames` batch by batch (under `torch.inference_mode`, float16 autocast on CUDA with `spec.amp`) and
    hand each prediction to `write(frame, prediction)` as soon as its batch is done; returns the seconds of inference
    (reading not counted). `task`: 'segmentation' or 'depth'. `rgb`: where the frames' RGB comes from (the stage's
    `FrameRgb`, shared by its passes); default a `FrameRgb` of this call, reading through the `image_loader` of
    `spec.loader_workers` processes."""
    import torch

    predict = seg.predict if task == "segmentation" else dep.predict
    if task == "segmentation":
        model = seg.for_inference(model)
    dev = next(model.parameters()).device
    rgb = rgb if rgb is not None else FrameRgb(spec.loader_workers, hold_bytes=0)
    seconds, done = 0.0, 0
    with torch.inference_mode():
        for images in tqdm(rgb.batches(frames, spec.predict_batch, dev), total=-(-len(frames) // spec.predict_batch),
                           desc=desc, disable=not progress, leave=False):
            t0 = time.perf_counter()
            out = predict(model, images, spec.predict_batch, amp=spec.amp)
            seconds += time.perf_counter() - t0
            for f, p in zip(frames[done : done + len(out)], out):
                write(f, p)
            done += len(out)
    return seconds


def _predict_all(study: Study, name: str, model, frames, progress: bool,
                 rgb: Optional[FrameRgb] = None) -> tuple[int, int, float]:
    """Predict the frames whose prediction file is missing, each written (atomically) as its batch is done, so a
    stopped run loses nothing predicted and the next one writes only the rest.

    The batches are always the same runs of `predict_batch` frames of `frames`, and every batch holding a missing
    frame is predicted whole (only its missing frames are written): on the CPU a prediction depends, in its last
    bits, on the size of its batch, so a resumed run gives the uninterrupted run's predictions bit for bit.
    Returns (frames written, frames through the network, seconds of inference)."""
    _, task = _spec(study, name)
    b = study.perception.predict_batch
    missing = {f.key for f in frames if not prediction_path(study, name, f).is_file()}
    batches = [frames[i : i + b] for i in range(0, len(frames), b)]
    todo = [f for batch in batches if any(g.key in missing for g in batch) for f in batch]
    dtype = np.int16 if task == "segmentation" else np.float32

    def write(frame, prediction):
        if frame.key in missing:
            io.write_h5(prediction_path(study, name, frame), prediction.astype(dtype))

    if not todo:
        return 0, 0, 0.0
    return len(missing), len(todo), predict_frames(model, task, todo, study.perception, write, progress,
                                                   f"predict {name}", rgb)


def _evaluate(study: Study, name: str, test) -> dict:
    _, task = _spec(study, name)
    if task == "segmentation":
        read = semantic_source(study, name)
        return evaluate_segmentation((f.semantic, read(f)) for f in test)
    read = depth_source(study, name)
    return evaluate_depth((f.depth, read(f)) for f in test)


def _rows(study: Study, name: str) -> list[dict]:
    spec, task = _spec(study, name)
    m = io.load_cached(model_dir(study, name) / "metrics.json", io.read_json_dict, f"test metrics of {name}")
    if m is None:
        return []
    role = "DeepLabV3" if task == "segmentation" else spec.role
    keys = ["pixel_accuracy", "miou"] if task == "segmentation" else ["abs_rel", "rmse", "delta1", "median_ratio",
                                                                      "nonfinite_share"]
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


def check_weights(study: Study) -> None:
    """The perception stage's check before any work: every shipped weights file of the study (`weights:`) has its
    manifest, and the manifest's network is the one its spec builds (`manifests.check_architecture`, no hashing:
    the file's sha256 is checked when it loads). One `StudyError` naming the spec's key otherwise."""
    for where, spec, task in study.perception_specs():
        if spec.weights:
            try:
                manifests.check_architecture(spec, task, resolve_path(spec.weights), f"{where}.weights")
            except manifests.WeightsError as exc:
                raise StudyError(str(exc)) from None


def run(study: Study, progress: bool = True, only: Optional[list[str]] = None, dataset=None,
        rgb: Optional[FrameRgb] = None) -> pd.DataFrame:
    """Train/evaluate/predict each perception model unless cached; returns the metrics table.

    `only`: model names to run (default all). `rgb`: where the models read the frames' RGB (a caller's `FrameRgb`,
    shared with its other passes); default one for this call, so that the models read each frame once. The table's
    ``attrs["status"]`` maps each model to 'cached' (nothing done), or 'done' (something was trained, evaluated or
    predicted).
    """
    check_weights(study)
    names = only or study.model_names()
    status: dict[str, str] = {}
    ds = dataset
    sels: dict[int, object] = {}
    rgb = rgb if rgb is not None else FrameRgb(study.perception.loader_workers)
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
            if _complete(study, name, frames):
                msg = f"perception: {tag} cached ({len(keys)} frames), nothing to do"
                print(msg)
                status[name] = "cached"
                continue
            model, history, how = _train_or_load(study, name, sel, progress)
            n_pred, n_run, secs = _predict_all(study, name, model, frames, progress, rgb)
            metrics = _evaluate(study, name, sel.test)
            if metrics.get("nonfinite_share", 0.0) > MAX_NONFINITE_SHARE:  # before anything marks it done
                raise NonFiniteDepth(
                    f"perception model {name!r} ({model_dir(study, name)}): {metrics['nonfinite_share']:.2%} of its "
                    f"predicted test pixels are NaN or inf (at most {MAX_NONFINITE_SHARE:.1%} allowed); its metrics "
                    f"and graphs are not made from them. Train it again (delete that folder) or check its weights")
            old = model_dir(study, name) / "metrics.json"
            old_ms = (io.load_cached(old, io.read_json_dict, f"test metrics of {name}")
                      or {}).get("inference_ms_per_frame")
            metrics.update(
                train_seconds=float(history.get("train_seconds", float("nan"))),
                inference_ms_per_frame=(1000.0 * secs / n_run) if n_run else old_ms,
                test_frames=len(sel.test), frames=len(keys), key=model_key(study, name),
            )
            io.write_json(model_dir(study, name) / "metrics.json", metrics)
            io.write_json(predictions_dir(study, name) / "_complete.json", {"model": name, "frames": sorted(keys)})
            status[name] = "done"
            shown = {k: round(v, 4) for k, v in metrics.items()
                     if k in ("pixel_accuracy", "miou", "abs_rel", "rmse", "delta1", "median_ratio")}
            print(f"perception: {tag} {how}, predicted {n_pred} frames, test {shown}")
    table = metrics_table(study)
    csv = table.to_csv(index=False, float_format="%.6g")
    # one per study sharing runs/<base>/
    _write_if_changed(study.data_dir / "perception" / f"metrics_{study.name}.csv", csv)
    _write_if_changed(paths.figures_dir(study.name) / "perception.csv", csv)
    table.attrs["status"] = status
    return table


def load_trained(study: Study, name: str):
    """The trained model `name` of the study from its cache (for the localizer); one clear error when missing."""
    spec, task = _spec(study, name)
    path = model_dir(study, name) / "model.pt"
    model = io.load_cached(path, lambda p: (seg if task == "segmentation" else dep).load_model(spec, p),
                           f"weights of {name}")
    if model is None:
        raise io.DataFileError(f"{path}: model {name!r} is not trained (or its file was unreadable); run "
                               f"`monolib perception {study.path or study.name}` first")
    return (seg.for_inference(model) if task == "segmentation" else model).eval()
