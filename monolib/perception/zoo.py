"""The model zoo: perception networks the project pretrains on its own mini-Hypersim and ships, as the paper used
AdelaiDepth "out of the box".

`make zoo` (= ``monolib zoo zoo``) renders the pretraining mini-Hypersim of ``params/zoo.yaml`` (its own seed, so its
settings share no room, material or camera with any study's test settings), trains the study's segmentation net
and depth nets on it, evaluates each on the test split of an evaluation study (``--eval``, default the quick study),
and writes, per network, into ``monolib/resources/zoo/`` (or ``--out``):

    <name>.pt     the weights in half precision: ``{"state_dict": ..., "architecture": ...}``
    <name>.json   the manifest: the command and study file that made it, the pretraining data's key, the machine and
                  device, the training time, the test metrics of the shipped (half-precision) file on the evaluation
                  study's test split, its size and sha256

A study uses them with ``weights: <path to the .pt>`` in a perception model's spec (next to ``pretrained``, which stays
for torchvision's ImageNet weights, and ``checkpoint``, for AdelaiDepth's own files): the perception stage then loads
the file instead of training. A file whose sha256 is not its manifest's, or whose architecture is not the spec's,
is one clear error (`WeightsError`).
"""
from __future__ import annotations

import dataclasses
import platform
import time
from pathlib import Path
from typing import TYPE_CHECKING, Optional

from monolib import io, paths
from monolib.data import dataset, selection
from monolib.device import device
from monolib.params import Study
from monolib.perception import depth as dep, imagenet, predictions, segmentation as seg
from monolib.perception.manifests import STAGING, WeightsError, architecture, read_manifest  # noqa: F401 (zoo.*)
from monolib.perception.weights import load  # (re-exported: zoo.load)

if TYPE_CHECKING:
    import pandas as pd

ZOO_DIR = paths.RESOURCES / "zoo"


sha256 = io.sha256


def export(model, spec, task: str, out: Path, info: dict) -> dict:
    """Write ``<out>/<name>.pt`` (half precision) and return the manifest fields of the file (sha256, size)."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{spec.name}.pt"
    state = {k: (v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu())
             for k, v in model.state_dict().items()}
    io.save_torch(path, {"state_dict": state, "architecture": architecture(spec, task)})
    return {"file": path.name, "bytes": path.stat().st_size, "sha256": sha256(path), **info}


def _machine() -> dict:
    import os

    import torch

    dev = device()
    return {"machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
            "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
            "torch": torch.__version__, "python": platform.python_version(), "date": time.strftime("%Y-%m-%d")}


def _relative(path: Optional[str]) -> Optional[str]:
    if not path:
        return path
    p = Path(path).resolve()
    return str(p.relative_to(paths.ROOT)) if p.is_relative_to(paths.ROOT) else str(p)


def _test_metrics(model, task: str, test_frames, images, batch: int = 16) -> dict:
    """Metrics of `model` on the evaluation study's test frames (`images`: their RGB, read once)."""
    predict = seg.predict if task == "segmentation" else dep.predict
    pairs = []
    for i in range(0, len(test_frames), batch):
        pred = predict(model, images[i : i + batch], batch)
        pairs += [((f.semantic if task == "segmentation" else f.depth), p)
                  for f, p in zip(test_frames[i : i + batch], pred)]
    metrics = predictions.evaluate_segmentation(pairs) if task == "segmentation" else predictions.evaluate_depth(pairs)
    return {k: v for k, v in metrics.items()}


CURVE_KEYS = {"segmentation": ("pixel_accuracy", "miou"), "depth": ("delta1", "abs_rel")}


def _up_to_date(out: Path, name: str, key: str) -> Optional[dict]:
    """The shipped manifest of `name` when it names this model key, holds test metrics and its weights' hash
    matches; None when the network must be trained (again)."""
    mpath = out / f"{name}.json"
    old = io.load_cached(mpath, io.read_json_dict, f"manifest of {name}")
    if old and old.get("model_key") == key and "test_metrics" in old and (out / f"{name}.pt").is_file() \
            and sha256(out / f"{name}.pt") == old.get("sha256"):
        print(f"zoo: {name} up to date ({mpath})", flush=True)
        return old
    return None


def _ship(model, spec, task: str, out: Path, info: dict, evaluation: Study, test, images) -> dict:
    """Export `model` in half precision into ``out/.staging/``, measure the file that ships on `evaluation`'s test
    split, then move weights and manifest into place (weights first); the manifest."""
    name = info["network"]
    stage = out / STAGING
    manifest = export(model, spec, task, stage, info)
    shipped = load(spec, task, stage / f"{name}.pt", manifest=manifest)  # the metrics of the file that ships
    metrics = _test_metrics(shipped, task, test, images)
    manifest.update(test_metrics=metrics, evaluated_on={
        "study": evaluation.name, "study_file": _relative(evaluation.path),
        "data_key": dataset.dataset_key(evaluation), "test_frames": len(test)})
    io.write_json(stage / f"{name}.json", manifest)
    (stage / f"{name}.pt").replace(out / f"{name}.pt")
    (stage / f"{name}.json").replace(out / f"{name}.json")
    shown_m = {k: round(v, 3) for k, v in metrics.items() if k in ("pixel_accuracy", "miou", "delta1", "abs_rel")}
    print(f"zoo: {name} written ({manifest['bytes'] / 1e6:.1f} MB, {info['train_seconds'] / 60:.1f} min of "
          f"training), {evaluation.name} test split: {shown_m}", flush=True)
    return manifest


def run(zoo: Study, evaluation: Study, out: Optional[Path] = None, progress: bool = True,
        only: Optional[list[str]] = None) -> dict[str, dict]:
    """Train every perception network of the `zoo` study on its mini-Hypersim, evaluate the half-precision file
    on `evaluation`'s test split, write weights and manifests into `out` (default `ZOO_DIR`).

    Resumable: a network whose manifest already names this pretraining data, spec and code is skipped; a training
    run goes on after its last finished epoch (``runs/zoo/training/<name>-<key>.pt``, written after every epoch);
    a run killed during evaluation or export resumes from that file without training again. After every epoch the
    network is measured on the evaluation study's test split too (the learning curve: accuracy against CPU
    minutes, recorded in the manifest's ``curve``; model selection uses the zoo's own validation settings only).
    The weights and their manifest are written as a pair: both into ``.staging/`` first, then moved into place,
    the weights first; a kill between the two moves leaves the new manifest in ``.staging/``, and the next reader
    of that pair moves it into place (`manifests.finish_pending_pair`), so a study never sees new weights beside an
    old manifest.
    """
    import numpy as np

    out = Path(out) if out else ZOO_DIR
    zoo_ds = dataset.ensure_dataset(zoo, progress=progress)
    eval_ds = dataset.ensure_dataset(evaluation, progress=progress)
    manifests = {}
    test = images = None
    for name in only or zoo.model_names():
        spec, task = predictions._spec(zoo, name)
        key = predictions.model_key(zoo, name)
        old = _up_to_date(out, name, key)
        if old is not None:
            manifests[name] = old
            continue
        if test is None:
            test = selection.select_frames(evaluation, eval_ds, spec.val_settings).test
            images = np.stack([f.rgb for f in test])
        sel = selection.select_frames(zoo, zoo_ds, spec.val_settings)
        mod = seg if task == "segmentation" else dep
        source = imagenet.source(spec.backbone) if spec.pretrained and imagenet.is_efficientnet(spec.backbone) else None
        print(f"zoo: training {name} ({task}, {spec.backbone}{', ImageNet ' + source['package'] if source else ''}, "
              f"{spec.epochs} epochs, {len(sel.train)} frames at {spec.train_width}x{spec.train_height}); after "
              f"each epoch: {evaluation.name} test split ({len(test)} frames)", flush=True)
        shown = CURVE_KEYS[task]

        def on_epoch(model, rec, spec=spec, task=task):
            m = _test_metrics(model, task, test, images)
            rec.update({f"test_{k}": m[k] for k in shown})
            print(f"zoo: {spec.name} epoch {rec['epoch']}/{spec.epochs}: train loss {rec['train_loss']:.3f}, "
                  f"{evaluation.name} test " + ", ".join(f"{k} {m[k]:.3f}" for k in shown) +
                  f", {rec['train_seconds'] / 60:.1f} min of training", flush=True)

        resume = paths.RUNS / zoo.name / "training" / f"{name}-{key}.pt"
        resume.parent.mkdir(parents=True, exist_ok=True)
        with predictions._threads(zoo.perception.threads):
            model, history = mod.train(spec, sel.train, sel.val, seed=zoo.seed, progress=progress,
                                       deterministic=zoo.deterministic, resume=resume, on_epoch=on_epoch)
        train_seconds = history["train_seconds"]
        curve = [{"epoch": r["epoch"], "train_minutes": round(r["train_seconds"] / 60, 2),
                  **{f"test_{k}": r.get(f"test_{k}") for k in shown},
                  **{k: r[k] for k in r if k.startswith("val_")}} for r in history["epochs"]]
        info = {"network": name, "task": task, "architecture": architecture(spec, task),
                "command": f"monolib zoo {_relative(zoo.path)} --eval {_relative(evaluation.path)}",
                "study_file": _relative(zoo.path),
                "data_key": dataset.dataset_key(zoo), "model_key": key, "seed": zoo.seed,
                "spec": dataclasses.asdict(spec), "imagenet": source, "train_frames": len(sel.train),
                "val_frames": len(sel.val), "epochs": len(history["epochs"]), "best_epoch": history.get("best_epoch"),
                "train_seconds": round(train_seconds, 1), "threads": zoo.perception.threads, "curve": curve,
                **_machine()}
        manifests[name] = _ship(model, spec, task, out, info, evaluation, test, images)
    if out == ZOO_DIR and manifests:  # the shipped zoo: its curves beside the study's results
        write_figures(shipped_manifests(zoo, out), paths.FIGURES)
    return manifests


def shipped_manifests(zoo: Study, out: Optional[Path] = None) -> dict[str, dict]:
    """The finished manifests of the zoo study's networks in `out` (default `ZOO_DIR`), in the study's order."""
    out = Path(out) if out else ZOO_DIR
    found = {}
    for name in zoo.model_names():
        m = io.load_cached(out / f"{name}.json", io.read_json_dict, f"manifest of {name}") \
            if (out / f"{name}.json").is_file() else None
        if m and "test_metrics" in m:
            found[name] = m
    return found


# (height, width, epochs): sides multiples of 32 (DeepLabV3 on EfficientNet at stride 16); a quarter of the epochs at
# four times the pixels, so that both curves span about the same CPU minutes
PILOT_SIZES = ((96, 128, 8), (192, 256, 2))


def pilot(zoo: Study, evaluation: Study, out: Path, frames: int = 300,
          sizes=PILOT_SIZES, progress: bool = False, only: Optional[list[str]] = None,
          test_every: int = 4) -> "pd.DataFrame":
    """The learning curve that sized `make zoo`: each network of the zoo study trained at each size of `sizes`
    on `frames` training frames (every n-th, spread over the settings) for its number of epochs, measured after every
    epoch on every `test_every`-th frame of `evaluation`'s test split; accuracy against CPU minutes (evaluation not
    counted), written to ``<out>/zoo_pilot.csv`` and ``.md`` after every epoch. A measurement on the machine it runs
    on (like `monolib bench`), not a cached stage."""
    import numpy as np
    import pandas as pd

    zoo_ds = dataset.ensure_dataset(zoo, progress=progress)
    eval_ds = dataset.ensure_dataset(evaluation, progress=progress)
    rows = []

    def write(test_frames: int):
        table = pd.DataFrame(rows)
        out.mkdir(parents=True, exist_ok=True)
        io.write_text(out / "zoo_pilot.csv", table.to_csv(index=False))
        io.write_text(out / "zoo_pilot.md",
                      f"# The zoo's learning curve: accuracy against CPU minutes (`make zoo-pilot`)\n\n"
                      f"{_machine()['machine']}, {zoo.perception.threads} torch threads, {_machine()['date']}: each "
                      f"network of `{_relative(zoo.path)}` from its ImageNet encoder, {frames} training frames, "
                      f"one-cycle schedule over the epochs of each size, measured after every epoch on {test_frames} "
                      f"test frames of `{evaluation.name}` (every {test_every}th) at their full size; "
                      f"minutes of training only.\n\n"
                      + table.to_markdown(index=False) + "\n")
        return table

    for name in only or zoo.model_names():
        spec, task = predictions._spec(zoo, name)
        sel = selection.select_frames(zoo, zoo_ds, spec.val_settings)
        test = selection.select_frames(evaluation, eval_ds, spec.val_settings).test[::test_every]
        images = np.stack([f.rgb for f in test])
        train = sel.train[:: max(1, len(sel.train) // frames)][:frames]
        for h, w, epochs in sizes:
            s = dataclasses.replace(spec, epochs=epochs, train_height=h, train_width=w)

            def on_epoch(model, rec, s=s, task=task, h=h, w=w, name=name, epochs=epochs):
                m = _test_metrics(model, task, test, images)
                rows.append({"network": name, "backbone": s.backbone, "size": f"{w}x{h}", "frames": len(train),
                             "epoch": rec["epoch"], "train_minutes": round(rec["train_seconds"] / 60, 2),
                             **{k: round(m[k], 4) for k in CURVE_KEYS[task]}})
                print(f"pilot: {name} {w}x{h} epoch {rec['epoch']}/{epochs}: " +
                      ", ".join(f"{k} {m[k]:.3f}" for k in CURVE_KEYS[task]) +
                      f" after {rec['train_seconds'] / 60:.1f} min", flush=True)
                write(len(test))

            mod = seg if task == "segmentation" else dep
            with predictions._threads(zoo.perception.threads):
                mod.train(s, train, [], seed=zoo.seed, progress=progress, deterministic=zoo.deterministic,
                          on_epoch=on_epoch)
    return pd.DataFrame(rows)


def curve_table(manifests: dict[str, dict]) -> "pd.DataFrame":
    """Every shipped network's learning curve from its manifest: one row per epoch (minutes of CPU training, test
    metrics on the evaluation study, validation metrics), then its shipped file's test metrics."""
    import pandas as pd

    rows = []
    for name, m in manifests.items():
        for c in m.get("curve", []):
            rows.append({"network": name, "backbone": m["spec"]["backbone"],
                         "size": f"{m['spec']['train_width']}x{m['spec']['train_height']}", **c})
    return pd.DataFrame(rows)


def write_figures(manifests: dict[str, dict], out: Path) -> None:
    """``<out>/zoo.md`` (each network: its data, time and machine, its learning curve on the evaluation study's test
    split, and the metrics of the shipped half-precision file) and ``<out>/zoo_curve.png`` (test metric against CPU
    minutes). Written by `run`; a pure function of the manifests."""
    import matplotlib

    matplotlib.use("agg")
    import matplotlib.pyplot as plt

    table = curve_table(manifests)
    lines = ["# The model zoo: ImageNet encoders fine-tuned on the CPU (`make zoo`)", ""]
    for name, m in manifests.items():
        src = m.get("imagenet") or {}
        tm = m["test_metrics"]
        shown = (f"pixel accuracy {tm['pixel_accuracy']:.3f}, mIoU {tm['miou']:.3f}" if m["task"] == "segmentation"
                 else f"delta<1.25 {tm['delta1']:.3f}, abs_rel {tm['abs_rel']:.3f}, rmse {tm['rmse']:.3f}")
        lines.append(
            f"- **{name}** ({m['task']}, {m['architecture']['model']} on {m['spec']['backbone']}, from "
            f"{src.get('package', 'random weights')} {src.get('version', '')} sha256 {src.get('sha256', '-')[:12]}): "
            f"{m['train_frames']} frames of `{m['study_file']}` at "
            f"{m['spec']['train_width']}x{m['spec']['train_height']}, "
            f"{m['epochs']} epochs (best {m['best_epoch']}) in {m['train_seconds'] / 60:.1f} min on {m['cpus']} CPUs "
            f"({m['machine']}, {m['device']}, {m['threads']} torch threads, {m['date']}); the shipped file "
            f"({m['bytes'] / 1e6:.1f} MB, float16) on the {m['evaluated_on']['test_frames']} test frames of "
            f"`{m['evaluated_on']['study']}`: {shown}")
    lines += ["", "Learning curves: after every epoch, the test split of the evaluation study (not used to choose the "
              "epoch: that is the validation settings of the zoo's own data).", "",
              table.to_markdown(index=False, floatfmt=".3f") if not table.empty else "_(no curve)_"]
    io.write_text(out / "zoo.md", "\n".join(lines) + "\n")
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for name, m in manifests.items():
        curve = table[table.network == name]
        if m["task"] == "segmentation":
            axes[0].plot(curve.train_minutes, curve.test_pixel_accuracy, "o-", label=f"{name} pixel accuracy")
            axes[0].plot(curve.train_minutes, curve.test_miou, "s--", label=f"{name} mIoU")
        else:
            axes[1].plot(curve.train_minutes, curve.test_delta1, "o-", label=f"{name} delta<1.25")
    for ax, title in zip(axes, ("semantics", "depth")):
        ax.set(xlabel="CPU minutes of training", ylim=(0, 1), title=f"{title}: quick's test split")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    io.save_figure(fig, out / "zoo_curve.png")
    plt.close(fig)
