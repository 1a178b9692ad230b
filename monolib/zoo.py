"""The model zoo: perception networks the project pretrains on its own mini-Hypersim and ships, as the paper used
AdelaiDepth "out of the box".

`make zoo` (= ``monolib zoo zoo``) renders the pretraining mini-Hypersim of ``params/zoo.yaml`` (its own seed, so its
settings share no room, material or camera with any study's test settings), trains the study's segmentation net
and depth nets on it, evaluates each on the test split of an evaluation study (``--eval``, default the quick study),
and writes, per network, into ``monolib/data/zoo/`` (or ``--out``):

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
import hashlib
import platform
import time
from pathlib import Path
from typing import Optional

from monolib import io, paths
from monolib.params import Study, StudyError, resolve_path

ZOO_DIR = paths.DATA / "zoo"


class WeightsError(StudyError):
    """Shipped weights that are missing, altered, or of another architecture than the study's spec."""


def architecture(spec, task: str) -> dict:
    """What a weights file must match to load into the network a spec builds."""
    from monolib.labels import NUM_CLASSES

    if task == "segmentation":
        return {"model": "deeplabv3", "backbone": spec.backbone, "classes": NUM_CLASSES,
                "input_size": [spec.train_height, spec.train_width]}
    return {"model": "leres_log_depth", "backbone": spec.backbone, "decoder_width": spec.decoder_width,
            "input_size": [spec.train_height, spec.train_width]}


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def manifest_path(weights: Path) -> Path:
    return Path(weights).with_suffix(".json")


def read_manifest(weights: Path, where: str = "weights") -> dict:
    """The manifest beside a weights file; `WeightsError` naming the file when it is absent or unreadable."""
    weights = Path(weights)
    m = manifest_path(weights)
    if not weights.is_file():
        raise WeightsError(f"{where}: file not found: {weights} (make it with `make zoo`)")
    try:
        manifest = io.read_json_dict(m, ("sha256", "architecture", "task"))
    except FileNotFoundError:
        raise WeightsError(f"{where}: {weights} has no manifest {m.name} beside it (shipped weights come with one)") from None
    except ValueError as exc:
        raise WeightsError(f"{m}: not a weights manifest ({exc})") from None
    return manifest


def check_architecture(spec, task: str, weights: Path, where: str = "weights") -> dict:
    """`WeightsError` when the manifest's architecture is not the one `spec` builds (no file hashing: cheap)."""
    manifest = read_manifest(weights, where)
    want, have = architecture(spec, task), manifest["architecture"]
    if manifest["task"] != task or want != have:
        diff = {k: (have.get(k), want.get(k)) for k in sorted(set(want) | set(have)) if have.get(k) != want.get(k)}
        raise WeightsError(f"{where}: {weights} holds a {manifest['task']} network {have}, the study's spec builds "
                           f"a {task} network {want} (differing: " +
                           ", ".join(f"{k} file {a!r} spec {b!r}" for k, (a, b) in diff.items()) + ")")
    return manifest


def load(spec, task: str, weights: str | Path, study_path: Optional[str] = None):
    """The network of `spec` with the shipped weights (float32, on `monolib.device.device()`), after checking the
    file's sha256 against its manifest and its architecture against the spec."""
    import torch

    from monolib import depth as dep
    from monolib import segmentation as seg

    path = resolve_path(str(weights), study_path)
    where = f"perception model {spec.name!r} weights"
    manifest = check_architecture(spec, task, path, where)
    digest = sha256(path)
    if digest != manifest["sha256"]:
        raise WeightsError(f"{where}: {path} has sha256 {digest[:16]}..., its manifest {manifest_path(path).name} "
                           f"says {manifest['sha256'][:16]}...: the file is not the one the manifest describes "
                           f"(altered or cut short); restore it from git or re-make it with `make zoo`")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    state = {k: (v.float() if v.is_floating_point() else v) for k, v in blob["state_dict"].items()}
    plain = dataclasses.replace(spec, pretrained=False) if dataclasses.is_dataclass(spec) else spec
    model = seg.build_model(plain) if task == "segmentation" else dep.build_model(plain)
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise WeightsError(f"{where}: {path} does not fit the network of the spec: {str(exc)[:300]}") from None
    from monolib.device import device

    return model.to(device()).eval()


def export(model, spec, task: str, out: Path, info: dict) -> dict:
    """Write ``<out>/<name>.pt`` (half precision) and return the manifest fields of the file (sha256, size)."""
    import torch

    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{spec.name}.pt"
    state = {k: (v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu())
             for k, v in model.state_dict().items()}
    io.save_torch(path, {"state_dict": state, "architecture": architecture(spec, task)})
    return {"file": path.name, "bytes": path.stat().st_size, "sha256": sha256(path), **info}


def _machine() -> dict:
    import os

    import torch

    from monolib.device import device

    dev = device()
    return {"machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
            "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu",
            "torch": torch.__version__, "python": platform.python_version(), "date": time.strftime("%Y-%m-%d")}


def _relative(path: Optional[str]) -> Optional[str]:
    if not path:
        return path
    p = Path(path).resolve()
    return str(p.relative_to(paths.ROOT)) if p.is_relative_to(paths.ROOT) else str(p)


def run(zoo: Study, evaluation: Study, out: Optional[Path] = None, progress: bool = True,
        only: Optional[list[str]] = None) -> dict[str, dict]:
    """Train every perception network of the `zoo` study on its mini-Hypersim, evaluate the half-precision file
    on `evaluation`'s test split, write weights and manifests into `out` (default `ZOO_DIR`). A network whose
    manifest already names this pretraining data, spec and code is skipped (resumable)."""
    import numpy as np

    from monolib import dataset, perception
    from monolib import depth as dep
    from monolib import segmentation as seg

    out = Path(out) if out else ZOO_DIR
    zoo_ds = dataset.ensure_dataset(zoo, progress=progress)
    eval_ds = dataset.ensure_dataset(evaluation, progress=progress)
    manifests = {}
    for name in only or zoo.model_names():
        spec, task = perception._spec(zoo, name)
        key = perception.model_key(zoo, name)
        mpath = out / f"{name}.json"
        old = io.load_cached(mpath, io.read_json_dict, f"manifest of {name}")
        if old and old.get("model_key") == key and "test_metrics" in old and (out / f"{name}.pt").is_file():
            print(f"zoo: {name} up to date ({mpath})", flush=True)
            manifests[name] = old
            continue
        sel = dataset.select_frames(zoo, zoo_ds, spec.val_settings)
        mod = seg if task == "segmentation" else dep
        print(f"zoo: training {name} ({task}, {spec.backbone}, {spec.epochs} epochs, {len(sel.train)} frames at "
              f"{spec.train_width}x{spec.train_height})", flush=True)
        t0 = time.perf_counter()
        with perception._threads(zoo.perception.threads):
            model, history = mod.train(spec, sel.train, sel.val, seed=zoo.seed, progress=progress,
                                       deterministic=zoo.deterministic)
        train_seconds = time.perf_counter() - t0
        info = {"network": name, "task": task, "architecture": architecture(spec, task),
                "command": f"monolib zoo {_relative(zoo.path)} --eval {_relative(evaluation.path)}",
                "study_file": _relative(zoo.path),
                "data_key": dataset.dataset_key(zoo), "model_key": key, "seed": zoo.seed,
                "spec": dataclasses.asdict(spec), "train_frames": len(sel.train), "val_frames": len(sel.val),
                "epochs": len(history["epochs"]), "best_epoch": history.get("best_epoch"),
                "train_seconds": round(train_seconds, 1), **_machine()}
        manifest = export(model, spec, task, out, info)
        io.write_json(mpath, manifest)  # without test metrics yet: `load` checks the file against it
        shipped = load(spec, task, out / f"{name}.pt")  # the metrics are those of the file that ships
        test = dataset.select_frames(evaluation, eval_ds, spec.val_settings).test
        predict = seg.predict if task == "segmentation" else dep.predict
        pairs = []
        for i in range(0, len(test), 16):
            chunk = test[i : i + 16]
            pred = predict(shipped, np.stack([f.rgb for f in chunk]), 16)
            pairs += [((f.semantic if task == "segmentation" else f.depth), p) for f, p in zip(chunk, pred)]
        metrics = (perception.evaluate_segmentation(pairs) if task == "segmentation"
                   else perception.evaluate_depth(pairs))
        manifest.update(test_metrics={k: v for k, v in metrics.items()}, evaluated_on={
            "study": evaluation.name, "study_file": _relative(evaluation.path), "data_key": dataset.dataset_key(evaluation),
            "test_frames": len(test)})
        io.write_json(mpath, manifest)
        manifests[name] = manifest
        shown = {k: round(v, 3) for k, v in metrics.items() if k in ("pixel_accuracy", "miou", "delta1", "abs_rel")}
        print(f"zoo: {name} written ({manifest['bytes'] / 1e6:.1f} MB, {train_seconds:.0f} s of training), "
              f"{evaluation.name} test split: {shown}", flush=True)
    return manifests
