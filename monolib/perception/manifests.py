"""The manifests of shipped weights (the zoo's ``<name>.json`` beside ``<name>.pt``): reading one and checking
that the network a perception spec builds is the one the file holds. No torch here: the perception stage checks a
study's weights with it when it starts (`monolib.perception.predictions.check_weights`), before any work;
`monolib.perception.zoo` writes the manifests and `monolib.perception.weights` loads the weights.
"""
from __future__ import annotations

from pathlib import Path

from monolib import io
from monolib.data.labels import NUM_CLASSES
from monolib.errors import StudyError


class WeightsError(StudyError):
    """Shipped weights that are missing, altered, or of another architecture than the study's spec."""


def architecture(spec, task: str) -> dict:
    """What a weights file must match to load into the network a spec builds."""
    if task == "segmentation":
        return {"model": "deeplabv3", "backbone": spec.backbone, "classes": NUM_CLASSES,
                "input_size": [spec.train_height, spec.train_width]}
    return {"model": "leres_log_depth", "backbone": spec.backbone, "decoder_width": spec.decoder_width,
            "input_size": [spec.train_height, spec.train_width]}


def manifest_path(weights: Path) -> Path:
    return Path(weights).with_suffix(".json")


STAGING = ".staging"  # where `monolib.perception.zoo` writes a new pair before moving it into place, weights first


def finish_pending_pair(weights: Path) -> bool:
    """Complete a pair whose export was cut between its two moves: the new weights are in place and their
    manifest still in ``.staging/`` (its weights moved out of it). Moves that manifest into place; True when it
    did. A pair with both files still in ``.staging/`` was cut before its first move: the old pair stands."""
    weights = Path(weights)
    staged = weights.parent / STAGING
    if (staged / manifest_path(weights).name).is_file() and not (staged / weights.name).exists() and weights.is_file():
        (staged / manifest_path(weights).name).replace(manifest_path(weights))
        return True
    return False


def read_manifest(weights: Path, where: str = "weights") -> dict:
    """The manifest beside a weights file (a pair cut between its two moves is completed first,
    `finish_pending_pair`); `WeightsError` naming the file when it is absent or unreadable."""
    weights = Path(weights)
    finish_pending_pair(weights)
    m = manifest_path(weights)
    if not weights.is_file():
        raise WeightsError(f"{where}: file not found: {weights} (make it with `make zoo`)")
    try:
        manifest = io.read_json_dict(m, ("sha256", "architecture", "task"))
    except FileNotFoundError:
        raise WeightsError(f"{where}: {weights} has no manifest {m.name} beside it "
                           "(shipped weights come with one)") from None
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
