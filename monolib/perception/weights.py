"""Shipped weights into their network: the file's sha256 against its manifest, its architecture against the
spec, then a strict load (`load`). Read by the perception stage (`monolib.perception.predictions`) and by the zoo
that writes the files (`monolib.perception.zoo`), which sits above it.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Optional

from monolib import io
from monolib.device import device
from monolib.params import resolve_path
from monolib.perception import depth as dep, segmentation as seg
from monolib.perception.manifests import WeightsError, check_architecture, manifest_path

sha256 = io.sha256


def load(spec, task: str, weights: str | Path, manifest: Optional[dict] = None):
    """The network of `spec` with the shipped weights (float32, on `monolib.device.device()`), after checking the
    file's sha256 against its manifest (the one beside it, or `manifest`) and its architecture against the spec."""
    import torch

    path = resolve_path(str(weights))
    where = f"perception model {spec.name!r} weights"
    if manifest is None:
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

    return model.to(device()).eval()
