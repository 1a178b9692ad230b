"""The version of the code behind each cached stage: part of every cache key, so a changed stage recomputes.

A stage's version is a hash of the source of the modules that compute its output (`STAGE_MODULES`), taken from
their syntax tree without docstrings: an edit to a comment, a docstring or the layout keeps the caches, any change
to the code (a constant of the graph builder, a layer of a network) gives new keys, and the stage and everything
after it run again on an existing ``runs/``. Each stage's key also holds the keys of its inputs (the dataset's in the
perception models', the models' in the graphs', the graphs' in the cells'), so a change propagates downstream.

A hash is conservative (a refactor that keeps every number still recomputes) but cannot be forgotten the way a
hand-bumped constant can. `monolib.data.synth.FORMAT_VERSION` stays as the rendered files' own format mark.
"""
from __future__ import annotations

import ast
import functools
import hashlib
from pathlib import Path

from monolib import paths

# The modules whose code decides each stage's output (the stage's own module and the ones it computes with).
STAGE_MODULES = {
    "dataset": ["data.dataset", "data.synth", "data.synth.materials", "data.synth.furniture", "data.synth.rooms",
                "data.synth.mesh", "data.synth.raycast", "data.synth.render", "data.synth.cameras",
                "data.synth.setting", "data.synth.dataset", "data.hypersim", "data.exact", "data.labels"],
    "perception": ["perception.predictions", "perception.images", "perception.segmentation", "perception.depth",
                   "perception.imagenet", "perception.zoo", "perception.manifests", "perception.weights",
                   "data.dataset", "data.selection", "data.folds", "data.protocols", "data.hypersim", "data.exact",
                   "data.labels"],
    "graphs": ["graphs.scenegraphs", "graphs.build", "data.dataset", "data.selection", "data.folds", "data.protocols",
               "data.hypersim", "data.exact", "graphs.published", "methods", "data.labels"],
    "features": ["perception.features", "perception.images", "perception.imagenet", "data.dataset", "data.selection",
                 "data.folds", "data.protocols", "data.hypersim", "data.exact", "data.labels"],
    "cells": ["retrieval.cell", "retrieval.gcn", "retrieval.training", "retrieval.baselines", "retrieval.pretrained",
              "retrieval.evaluate", "retrieval.metrics", "methods", "graphs.build", "data.dataset", "data.selection",
              "data.folds", "data.protocols", "data.hypersim", "data.exact", "data.labels"],
}
# What a stage's modules may import beyond their own list (`tests/test_cache.py` holds every import to this):
# upstream stages, whose keys are part of this stage's key, and infrastructure that computes no number. A new
# import outside these makes that test fail: add the module to the stage's list or here, with reason.
UPSTREAM = {"dataset": [], "perception": ["dataset"], "graphs": ["dataset", "perception"], "features": ["dataset"],
            "cells": ["dataset", "perception", "graphs", "features"]}
INFRASTRUCTURE = ["io", "paths", "params", "errors", "device", "versions", "progress", "locks"]
PRESENTATION: list[str] = []  # (every import points down the pipeline: no stage module imports the report or runner)


# The libraries whose versions decide each stage's numbers: part of the stage's key, next to its code's version.
STAGE_LIBRARIES = {
    "dataset": ["numpy", "trimesh", "embreex", "h5py"],
    "perception": ["torch", "torchvision", "timm", "segmentation_models_pytorch", "numpy"],
    "graphs": ["numpy", "torch"],
    "features": ["torch", "timm", "numpy"],
    "cells": ["torch", "torch_geometric", "numpy", "opencv-python-headless", "torchvision"],
}
# Functions of a stage's module that compute no cached output (a stage's figures live in `monolib.report`, outside
# every version): left out of its version, so that a change to one does not recompute the stage.
PRESENTATION_FUNCTIONS = {
    "perception.predictions": {"_write_if_changed"},  # the copy of the metrics table in figures/
}


@functools.lru_cache(maxsize=None)
def library_versions(stage: str) -> dict:
    """``{distribution: version or None}`` of `STAGE_LIBRARIES[stage]`."""
    from importlib import metadata

    out = {}
    for name in STAGE_LIBRARIES[stage]:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
                    and isinstance(body[0].value.value, str):
                node.body = body[1:] or [ast.Pass()]
    return tree


def source_version(source: str, filename: str = "<source>") -> str:
    """Hash of Python source without its comments, docstrings or layout."""
    tree = _strip_docstrings(ast.parse(source, filename=filename))
    return hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()[:12]


def module_file(module: str) -> Path:
    """The source file of a monolib module named relative to the package (``data.synth.rooms``, ``paths``):
    ``monolib/<a>/<b>.py``, or a package's ``monolib/<a>/<b>/__init__.py`` (which may not exist)."""
    path = paths.PACKAGE.joinpath(*module.split("."))
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


def module_version(module: str) -> str:
    """`source_version` of one module (`module_file`), its `PRESENTATION_FUNCTIONS` left out; computed once per
    state of its file (`file_version`)."""
    path = module_file(module)
    st = path.stat()
    return file_version(module, str(path), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=None)
def file_version(module: str, path: str, mtime_ns: int, size: int) -> str:
    """`module_version` of `module` whose file `path` has this modification time and size: cached by them, so that
    the cache cannot hold a changed file's hash, and a warm kernel keeps it from cell to cell
    (`monolib.study.kernels.reset_kernel`: parsing the stages' modules took about 0.5 s a cell)."""
    path = Path(path)
    text = path.read_text()
    drop = PRESENTATION_FUNCTIONS.get(module)
    if drop:
        tree = ast.parse(text, str(path))
        tree.body = [n for n in tree.body if not (isinstance(n, ast.FunctionDef) and n.name in drop)]
        text = ast.unparse(tree)
    return source_version(text, str(path))


@functools.lru_cache(maxsize=None)
def code_version(stage: str) -> str:
    """The version of `stage` (a key of `STAGE_MODULES`): one hash over its modules' versions."""
    if stage not in STAGE_MODULES:
        raise KeyError(f"stage {stage!r}: unknown (known: {', '.join(STAGE_MODULES)})")
    text = ",".join(f"{m}:{module_version(m)}" for m in STAGE_MODULES[stage])
    return hashlib.sha256(text.encode()).hexdigest()[:12]
