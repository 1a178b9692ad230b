"""A localizer people can use: index the frames of known places, then find the place of new RGB images.

`monolib index STUDY --out DB` embeds the study's test frames with the encoder of one finished cell (by default the
best cell whose scenario uses predicted depth and predicted semantics, as a new image has neither) and stores
`embeddings.npy`, `frames.csv` and `meta.json` (study, cell, and the tags of the perception models) in DB.
`--method` names a graph method, or an image method (`monolib.methods`: colour histogram, ORB, the CNNs, the
ImageNet descriptors), whose best cell's descriptor (and its vocabulary or weights) then makes the database.
`monolib localize IMAGE... --db DB` runs segmentation, depth, graph and encoder on each image (an image method:
its descriptor alone) and prints the nearest settings. A new image is centre-cropped to 4:3, resized to the study's resolution and treated as a
Hypersim canonical camera (60 degree horizontal field of view).

Every bad input is one `LocalizeError` naming the file or option and what was expected (the command prints it as one
``error:`` line and exits with status 2): no database folder or a database file missing, `index` on a study without
a finished cell, an unknown `--method`, a database whose scenario or method is no longer in its study file, a
graph database of HDR node colours (`graphs.colour: hdr`: a photo has no HDR radiance, so `index` refuses such a
cell and `localize` such a database, naming the key), and a `--k` outside 1 .. the number of settings in the
database (see `localize`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch

from monolib import methods, paths
from monolib.data import selection, stage as dataset
from monolib.data.hypersim import Camera
from monolib.device import device
from monolib.graphs import build as graph, stage as scenegraphs
from monolib.graphs.build import scene_nodes
from monolib.io import DataFileError, atomic_path, read_json, save_torch, write_json, write_text
from monolib.params import PAPER, Study, load_study
from monolib.perception import depth as depth_mod, segmentation as seg_mod, stage as perception
from monolib.perception.images import FrameRgb
from monolib.report.results import cell_metrics
from monolib.retrieval import baselines, gcn, pretrained


class LocalizeError(RuntimeError):
    """A bad image, database or model; the message names the file."""


def read_image(path: str | Path) -> np.ndarray:
    """An RGB uint8 image from a PNG/JPEG file of any size."""
    path = Path(path)
    if not path.is_file():
        raise LocalizeError(f"{path}: image file not found")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise LocalizeError(f"{path}: not a readable image (expected PNG or JPEG)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def to_study_frame(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """Centre-crop to 4:3 and resize to the study's frame size."""
    h, w = rgb.shape[:2]
    if w * 3 > h * 4:
        cw = h * 4 // 3
        rgb = rgb[:, (w - cw) // 2 : (w - cw) // 2 + cw]
    else:
        ch = w * 3 // 4
        rgb = rgb[(h - ch) // 2 : (h - ch) // 2 + ch]
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _image_method(study: Study, method: str | None) -> bool:
    return method is not None and method in study.methods and methods.kind(method, study) == "image"


def pick_cell(study: Study, method: str | None = None) -> dict:
    """The finished graph-method cell (of `method`, or of any) with the best recall@1 (``paper`` protocol) among
    scenarios with predicted depth, predicted semantics and tonemapped node colours (what a new image has: a photo
    holds no HDR radiance, so an encoder trained on `graphs.colour: hdr` cannot read its graph; `HDR_REFUSED`);
    for an image method, its best cell (with its ``model.pt`` where the method learns something)."""
    image = _image_method(study, method)
    if method is not None and not image and method not in study.graph_methods():
        known = study.graph_methods() + [m for m in study.methods if methods.kind(m, study) == "image"]
        raise LocalizeError(f"{study.path}: --method {method}: not a method of study {study.name}; expected one "
                            f"of {', '.join(known)}")
    best, hdr_only = None, False
    wanted = [method] if method else study.graph_methods()
    files = [f for m in wanted for f in sorted((paths.study_dir(study.name) / "cells" / m).glob("*/cell.json"))]
    for f in files:
        c = read_json(f)
        if not image:
            sc = study.scenarios.get(c["scenario"])
            if sc is None or sc.depth == "gt" or sc.semantic == "gt" or sc.depth_scale != 1.0:
                continue
            if study.colour(c["scenario"]) != "tonemapped":
                hdr_only = True
                continue
        if (not image or method in STATEFUL) and not (f.parent / "model.pt").is_file():
            continue
        if best is None or cell_metrics(c)[PAPER]["recall@1"] > cell_metrics(best[0])[PAPER]["recall@1"]:
            best = (c, f.parent)
    if best is None and hdr_only:
        raise LocalizeError(f"{study.path}: {HDR_REFUSED} Index an image method (--method), or a study whose "
                            f"scenario with predicted inputs has `colour: tonemapped` (the ablations study's "
                            f"s3_tonemapped).")
    if best is None:
        what = (f"{method} cell" + (" with a saved model.pt" if method in STATEFUL else "") if image
                else f"{method or 'graph-method'} cell with predicted depth and semantics and a saved model.pt")
        raise LocalizeError(f"{paths.study_dir(study.name) / 'cells'}: no finished {what}; run "
                            f"`monolib study {study.name}` first")
    return {**best[0], "folder": str(best[1])}


HDR_REFUSED = ("graphs.colour: hdr: the encoders of this study's graph cells read node colours of HDR radiance "
               "(color.hdf5), which a photo does not have, so no graph database is built from them.")
# the image methods whose cell learns what their descriptor needs (a vocabulary, weights): its model.pt
STATEFUL = ("orb_bow", "image_triplet", "imagenet_vlad", "imagenet_triplet")


def image_describer(method: str, state: dict | None):
    """The descriptor function of an image method (`baselines.describer` or `pretrained.describer`)."""
    return (pretrained.describer if method in methods.IMAGENET else baselines.describer)(method, state)


def describe_frames(describe, frames, batch: int = 32) -> np.ndarray:
    """(N, D) float32: `describe` over the frames' RGB, in batches read in this process (`FrameRgb`)."""
    rgb = FrameRgb(0, hold_bytes=0).batches(frames, batch, torch.device("cpu"),
                                            "the RGB a database frame is described from")
    try:
        return np.concatenate([describe(images.numpy()) for images in rgb])
    except DataFileError as exc:
        raise LocalizeError(str(exc)) from None


def build_index(study: Study, out: str | Path, method: str | None = None) -> Path:
    """Write the database of the study's test frames (their embeddings and settings) into `out`."""
    out = Path(out)
    c = pick_cell(study, method)
    if _image_method(study, method):
        state_file = Path(c["folder"]) / "model.pt"
        state = torch.load(state_file, map_location="cpu", weights_only=True) if state_file.is_file() else {}
        test = selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings).test
        emb = describe_frames(image_describer(method, state), test)
        return write_database(out, study, c, state, [f.key for f in test], [f.setting for f in test], emb)
    spec = study.gcn_spec(c["method"])
    threshold = float(c["threshold"])  # "inf" reads as inf
    model = gcn.GraphEncoder(spec)
    model.load_state_dict(torch.load(Path(c["folder"]) / "model.pt", map_location="cpu", weights_only=True))
    model.to(device())
    projection = study.projection(c["scenario"])
    test = [gcn.encoder_graph(g, threshold, spec, projection) for g in scenegraphs.load(study, c["scenario"])["test"]]
    emb = gcn.embed(model, test).numpy().astype(np.float32)
    return write_database(out, study, c, model.state_dict(), [g.frame for g in test], [g.setting for g in test], emb)


META_KEYS = ("study", "study_file", "cell", "method", "scenario", "threshold", "seed", "models", "width", "height")
# a database whose meta.json names no `projection` holds graphs of the exact camera
DEFAULT_PROJECTION = "exact"


def write_database(out: str | Path, study: Study, cell: dict, state: dict | torch.nn.Module, frames: list[str],
                   settings: list[str], embeddings: np.ndarray) -> Path:
    """The database files: `embeddings.npy` (one row per frame), `frames.csv` (frame, setting), `encoder.pt` (the
    encoder's state: a graph encoder's weights; an image method's vocabulary or weights, empty for a descriptor that
    learns nothing) and `meta.json` (study, cell, kind, encoder and perception models). `cell` is the cell.json
    (with its ``folder``)."""
    out = Path(out)
    state = state.state_dict() if isinstance(state, torch.nn.Module) else state  # (an encoder: its weights)
    image = methods.kind(cell["method"], study) == "image"
    sc = None if image else study.scenarios[cell["scenario"]]
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "embeddings.npy") as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(embeddings, np.float32))
    write_text(out / "frames.csv", pd.DataFrame({"frame": frames, "setting": settings}).to_csv(index=False))
    save_torch(out / "encoder.pt", {k: v.detach().cpu() for k, v in state.items()})
    write_json(out / "meta.json", {
        "study": study.name, "study_file": study.path, "cell": cell["folder"], "method": cell["method"],
        "kind": "image" if image else "graph", "scenario": cell["scenario"],
        "threshold": cell["threshold"], "seed": cell["seed"], "cell_recall@1": cell_metrics(cell)[PAPER]["recall@1"],
        "models": {} if image else {"semantic": perception.model_tag(study, sc.semantic),
                                    "depth": perception.model_tag(study, sc.depth)},
        "width": study.dataset.width, "height": study.dataset.height, "frames": len(frames),
        # the query graphs are built in the database's camera (an image method builds none)
        "projection": None if image else study.projection(cell["scenario"]),
        "colour": None if image else study.colour(cell["scenario"]),
    })
    return out


def read_database(db: str | Path) -> tuple[dict, pd.DataFrame, np.ndarray]:
    """(meta, frames, embeddings) of a database folder, checked; no model is loaded."""
    db = Path(db)
    hint = f"build the database with `monolib index STUDY --out {db}`"
    if not db.is_dir():
        raise LocalizeError(f"{db}: no database folder; {hint}")
    for name in ("meta.json", "embeddings.npy", "frames.csv", "encoder.pt"):
        if not (db / name).is_file():
            raise LocalizeError(f"{db / name}: missing; {hint}")
    try:
        meta = read_json(db / "meta.json")
    except ValueError as exc:
        raise LocalizeError(f"{db / 'meta.json'}: not valid JSON ({exc}); {hint}") from None
    missing = [k for k in META_KEYS if not isinstance(meta, dict) or k not in meta]
    if missing:
        raise LocalizeError(f"{db / 'meta.json'}: no key {missing[0]!r}; expected the keys {', '.join(META_KEYS)}")
    try:
        frames = pd.read_csv(db / "frames.csv")
        emb = np.load(db / "embeddings.npy")
    except Exception as exc:
        raise LocalizeError(f"{db}: unreadable frames.csv or embeddings.npy ({exc}); {hint}") from None
    if not {"frame", "setting"} <= set(frames.columns) or emb.ndim != 2 or len(emb) != len(frames):
        raise LocalizeError(f"{db}: frames.csv (columns {list(frames.columns)}, {len(frames)} rows) and embeddings.npy "
                            f"(shape {list(emb.shape)}) disagree; expected columns frame, setting and one embedding "
                            f"row per frame")
    return meta, frames, emb


@dataclass
class Localizer:
    study: Study
    meta: dict
    segmentation: torch.nn.Module | None
    depth: torch.nn.Module | None
    encoder: gcn.GraphEncoder | None
    embeddings: torch.Tensor
    frames: pd.DataFrame
    describe: object = None  # an image method's descriptor function (`image_describer`); None for a graph method

    @staticmethod
    def open(db: str | Path) -> "Localizer":
        db = Path(db)
        meta, frames, emb = read_database(db)
        study = load_study(meta["study_file"], check_files=False)
        rebuild = f"rebuild the database with `monolib index {study.name} --out {db}`"
        if meta.get("kind") == "image":
            if meta["method"] not in study.methods:
                raise LocalizeError(f"{db / 'meta.json'}: image method {meta['method']!r} is not a method of the study "
                                    f"file {study.path} (its methods: {', '.join(study.methods)}); {rebuild}")
            state = torch.load(db / "encoder.pt", map_location="cpu", weights_only=True)
            return Localizer(study, meta, None, None, None, torch.from_numpy(emb), frames,
                             image_describer(meta["method"], state))
        if meta["scenario"] not in study.scenarios:
            raise LocalizeError(f"{db / 'meta.json'}: scenario {meta['scenario']!r} is not in the study file "
                                f"{study.path} (its scenarios: {', '.join(study.scenarios)}); {rebuild}")
        if meta["method"] not in study.graph_methods():
            raise LocalizeError(f"{db / 'meta.json'}: method {meta['method']!r} is not a graph method of the study file "
                                f"{study.path} (its graph methods: {', '.join(study.graph_methods())}); {rebuild}")
        if study.colour(meta["scenario"]) != meta.get("colour", "tonemapped"):
            raise LocalizeError(f"{db / 'meta.json'}: node colours {meta.get('colour', 'tonemapped')!r}, but scenario "
                                f"{meta['scenario']!r} of {study.path} now has graphs.colour "
                                f"{study.colour(meta['scenario'])!r}; {rebuild}")
        if meta.get("colour", "tonemapped") != "tonemapped":
            raise LocalizeError(f"{db / 'meta.json'}: {HDR_REFUSED}")
        sc = study.scenarios[meta["scenario"]]
        now = {"semantic": perception.model_tag(study, sc.semantic), "depth": perception.model_tag(study, sc.depth)}
        if now != meta["models"]:
            raise LocalizeError(f"{db / 'meta.json'}: the database was made by models {meta['models']}, but study "
                                f"{study.name} now has {now}; rebuild it with `monolib index`")
        seg = perception.load_trained(study, sc.semantic)  # an untrained model: one DataFileError naming its file
        dep = perception.load_trained(study, sc.depth)
        encoder = gcn.GraphEncoder(study.gcn_spec(meta["method"]))
        encoder.load_state_dict(torch.load(db / "encoder.pt", map_location="cpu", weights_only=True))
        encoder.to(device()).eval()  # the networks run on the GPU when there is one; embeddings come back on the CPU
        return Localizer(study, meta, seg, dep, encoder, torch.from_numpy(emb), frames)

    def stages(self, rgb: np.ndarray, timings: dict | None = None) -> torch.Tensor:
        """The per-image pipeline: segmentation, depth, back-projection + graph, encoder -> (D,) embedding; an
        image method's descriptor alone for an image database."""
        t = time.perf_counter()
        w, h = self.meta["width"], self.meta["height"]
        frame = to_study_frame(rgb, w, h)
        if self.describe is not None:  # an image method: its descriptor is the whole pipeline
            z = torch.from_numpy(self.describe(frame[None])[0])
            if timings is not None:
                timings.setdefault("descriptor", []).append(time.perf_counter() - t)
            return z
        semantic = seg_mod.predict(self.segmentation, frame[None])[0]
        t1 = time.perf_counter()
        depth = depth_mod.predict(self.depth, frame[None])[0]
        t2 = time.perf_counter()
        projection = self.meta.get("projection", DEFAULT_PROJECTION)
        x, pos = scene_nodes(frame, depth, semantic, Camera.canonical(w, h), projection)
        threshold = float(self.meta["threshold"])  # "inf" reads as inf
        g = gcn.encoder_graph(graph.complete_graph(x, pos, "query", "query"), threshold, self.encoder.spec, projection)
        t3 = time.perf_counter()
        z = gcn.embed(self.encoder, [g])[0]
        t4 = time.perf_counter()
        if timings is not None:
            for k, v in (("segmentation", t1 - t), ("depth", t2 - t1), ("graph", t3 - t2), ("encoder", t4 - t3)):
                timings.setdefault(k, []).append(v)
        return z

    def query(self, rgb: np.ndarray, k: int = 5) -> list[dict]:
        """The k nearest settings (by their closest frame) with distances and the closest frame."""
        z = self.stages(rgb)
        d = torch.cdist(z[None], self.embeddings)[0].numpy()
        df = self.frames.assign(distance=d).sort_values("distance", kind="stable")
        best = df.groupby("setting", sort=False).head(1).head(k)
        return [{"rank": i + 1, "setting": r.setting, "distance": float(r.distance), "frame": r.frame}
                for i, r in enumerate(best.itertuples())]


DEFAULT_K = 5


def localize(images: list[str], db: str | Path, k: int | None = None) -> list[dict]:
    """The `k` nearest settings of each image (default: `DEFAULT_K`, or every setting of a smaller database).

    A `k` given must be 1 .. the number of settings in the database, else one `LocalizeError` before any model is
    loaded. A larger one is an error, not clamped: the localizer ranks settings (each by its closest frame), so it
    cannot list more than the database holds, and a clamp would silently print fewer matches than asked (a script
    reading ``--json`` would get fewer rows than it asked for); the error says the largest k the database allows."""
    if k is not None and k < 1:
        raise LocalizeError(f"--k {k}: expected at least 1 (the number of nearest settings to list)")
    _, frames, _ = read_database(db)
    n = int(frames["setting"].nunique())
    if k is None:
        k = min(DEFAULT_K, n)
    elif k > n:
        raise LocalizeError(f"--k {k}: the database {db} holds {n} settings; expected 1 to {n}")
    loc = Localizer.open(db)
    rgbs = [read_image(p) for p in images]  # every path checked before any work
    return [{"image": str(p), "matches": loc.query(rgb, k)} for p, rgb in zip(images, rgbs)]


def format_results(results: list[dict]) -> str:
    lines = []
    for r in results:
        lines.append(r["image"])
        lines += [f"  {m['rank']}. {m['setting']}  distance {m['distance']:.3f}  (closest frame {m['frame']})"
                  for m in r["matches"]]
    return "\n".join(lines)
