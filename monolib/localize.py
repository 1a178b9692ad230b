"""A localizer people can use: index images of known places, then find the place of new RGB images.

`monolib index STUDY --out DB` embeds the study's test frames (each setting a place) with the encoder of one
finished cell; `monolib index STUDY --places DIR --out DB` embeds a folder of the user's own images instead, one
subfolder per place. `monolib localize IMAGE... --db DB` runs segmentation, depth, graph and encoder on each image
(an image method: its descriptor alone) and prints the nearest places, each with its closest database image.

Which encoder. By default the best finished graph-method cell (``paper`` recall@1) whose scenario uses predicted
depth and predicted semantics, as a new image has neither, and node colours of the tonemapped image, as a photo
holds no HDR radiance. A study whose predicted-input scenarios read HDR node colours (`graphs.colour: hdr`, the
default study's) has no such cell: `index` then trains, once, the tonemapped twin of its best predicted-input cell
(`tonemapped_twin`: the same method, sources, threshold and seed, on the same frames' graphs rebuilt with node
colours of the tonemapped RGB), through the grid's own `run_cell`, keyed like a cell and cached in
``runs/<study>/localizer/cells/``; its graphs are cached with the study's other graphs under the twin scenario's
key. Nothing switches silently: `meta.json` and the printed line name the method, the cell (and the cell it is the
twin of) and the colour space. `--method` names a graph method, or an image method of the study, whose best cell's
descriptor (and its vocabulary or weights) then makes the database.

A database folder stands on its own: `meta.json` (the format, what made it, the models' specs, each state file's
sha256 and the code versions of the stages a query runs), `encoder.pt` (a graph encoder's weights, an image
method's state), `segmentation.pt` and `depth.pt` (copies of the perception models' weights; a graph method only),
`embeddings.npy`, `frames.csv` (one row per database image: its name, its place, the sha256 of a `--places` image)
and `thumbnails.npy` (a small copy of each database image, for `--show`). A query reads nothing else, so a database
works with the study's runs/ deleted and from a copy on another machine with the project installed. A database of
another format, whose state files are not those its `meta.json` names (other models), or made by other code of
the stages a query runs (their `monolib.versions.code_version`) is refused, naming what differs.

Places (`--places DIR`): each folder ``DIR/<place>/`` is a place and its ``.jpg``, ``.jpeg`` and ``.png`` files
(any case) its images. Other files, nested folders and files directly in DIR are skipped, listed in the printed
output and in `meta.json` (``skipped``); names starting with a dot are ignored. A place folder without an image, a
DIR without a place folder, or an image file that does not decode is an error naming it. Indexing DIR again into
the same DB embeds only the images whose content (sha256) the database does not hold for the same encoder and
models; images gone from DIR leave the database.

Images are read as a photo viewer shows them (`read_image`): EXIF orientation applied, grayscale to RGB, 16-bit
to its top 8 bits, transparency composited over white, and a large JPEG decoded at 1/2, 1/4 or 1/8 scale (libjpeg's
DCT scaling, Pillow's `draft`) so that memory stays bounded (a 12,000 x 9,000 photo decodes to 1,500 x 1,125); a
PNG is decoded whole, up to Pillow's decompression-bomb limit. Each image is then centre-cropped to 4:3, resized to
the study's resolution and treated as a Hypersim canonical camera (60 degree horizontal field of view).

Every bad input is one `LocalizeError` naming the file or option and what was expected (the command prints it as one
``error:`` line and exits with status 2). `--k` must be 1 .. the number of places in the database (see `localize`).
"""
from __future__ import annotations

import dataclasses
import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch
from PIL import Image, ImageOps, UnidentifiedImageError

from monolib import io, locks, methods, paths, versions
from monolib.data import dataset, labels as nyu40, selection
from monolib.data.hypersim import Camera
from monolib.device import device
from monolib.graphs import build as graph, scenegraphs
from monolib.graphs.build import grouped_median, pair_mask, scene_nodes
from monolib.io import DataFileError, atomic_path, read_json, save_torch, write_json, write_text
from monolib.params import PAPER, DepthSpec, GCNSpec, SegmentationSpec, Study, key_of, load_study
from monolib.perception import depth as depth_mod, predictions, segmentation as seg_mod
from monolib.perception.images import FrameRgb
from monolib.perception.inference import prepare_network
from monolib.report.results import cell_metrics
from monolib.retrieval import baselines, cell as cells, gcn, pretrained


class LocalizeError(RuntimeError):
    """A bad image, database or model; the message names the file."""


# ---- reading photos ------------------------------------------------------------------------------------------

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")  # the files of a place folder that are read (any case)
READ_FORMATS = ("JPEG", "MPO", "PNG")       # what `read_image` decodes (MPO: a JPEG with extra frames, from cameras)
DECODE_SCALE = 2  # a JPEG is decoded at the smallest DCT scale whose sides stay >= this x the study frame's long side


def read_image(path: str | Path, min_side: int | None = None) -> np.ndarray:
    """(H, W, 3) uint8 RGB of a PNG or JPEG file, as a photo viewer shows it: EXIF orientation applied, grayscale
    as RGB, 16 bits per channel to their top 8, transparency composited over white. `min_side`: a JPEG is decoded at
    the smallest 1/2, 1/4 or 1/8 scale whose width and height stay at least this (memory bounded by the decoded
    size, not the file's); None: full size."""
    path = Path(path)
    if not path.is_file():
        raise LocalizeError(f"{path}: image file not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # a JPEG decodes reduced; see below
            with Image.open(path) as im:
                if im.format not in READ_FORMATS:
                    raise LocalizeError(f"{path}: a {im.format} image; expected PNG or JPEG")
                if min_side and im.format != "PNG":
                    im.draft(None, (min_side, min_side))
                return _as_rgb(ImageOps.exif_transpose(im))
    except LocalizeError:
        raise
    except Image.DecompressionBombError as exc:
        raise LocalizeError(f"{path}: too large to decode ({exc})") from None
    except PermissionError as exc:
        raise LocalizeError(f"{path}: cannot be read ({exc.strerror})") from None
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise LocalizeError(f"{path}: not a readable image (expected PNG or JPEG; {exc})") from None


def _as_rgb(im: Image.Image) -> np.ndarray:
    """RGB uint8 of a decoded image of any mode Pillow gives a PNG or JPEG."""
    if im.mode.startswith("I"):  # 16-bit (or 32-bit integer) grayscale: its top 8 bits
        a = np.asarray(im).astype(np.int64)
        gray = np.clip(a >> 8 if a.max(initial=0) > 255 else a, 0, 255).astype(np.uint8)
        return np.ascontiguousarray(np.repeat(gray[..., None], 3, axis=2))
    if im.mode in ("RGBA", "LA", "PA", "RGBa", "La") or (im.mode == "P" and "transparency" in im.info):
        a = np.asarray(im.convert("RGBA")).astype(np.float32)
        alpha = a[..., 3:] / 255.0
        return np.rint(a[..., :3] * alpha + 255.0 * (1.0 - alpha)).astype(np.uint8)  # over white
    return np.ascontiguousarray(np.asarray(im.convert("RGB"), dtype=np.uint8))


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


# ---- the user's places ---------------------------------------------------------------------------------------

@dataclass
class Places:
    """A folder of places (`scan_places`): ``images[place]``: its images' paths relative to `root`, sorted;
    `skipped`: what was not read, each ``"relative path: why"``."""
    root: Path
    images: dict[str, list[str]]
    skipped: list[str]


def scan_places(folder: str | Path) -> Places:
    """The places of `folder` (``DIR/<place>/`` image files); see the module's docstring for what is skipped."""
    root = Path(folder)
    expected = "expected DIR/<place>/ folders of .jpg, .jpeg or .png images"
    if not root.is_dir():
        raise LocalizeError(f"{root}: --places: no such folder; {expected}")
    images: dict[str, list[str]] = {}
    skipped: list[str] = []
    for entry in sorted(root.iterdir()):
        if entry.name.startswith("."):
            continue
        if not entry.is_dir():
            skipped.append(f"{entry.name}: a file outside any place folder")
            continue
        files = []
        for f in sorted(entry.iterdir()):
            rel = f"{entry.name}/{f.name}"
            if f.name.startswith("."):
                continue
            if f.is_dir():
                skipped.append(f"{rel}/: a nested folder (a place is one folder of images)")
            elif f.suffix.lower() in IMAGE_SUFFIXES:
                files.append(rel)
            else:
                skipped.append(f"{rel}: not a .jpg, .jpeg or .png file")
        if not files:
            raise LocalizeError(f"{entry}: place folder {entry.name!r} holds no image; expected one or more .jpg, "
                                f".jpeg or .png files in it (or remove the folder)")
        images[entry.name] = files
    if not images:
        raise LocalizeError(f"{root}: --places holds no place folder; {expected}")
    return Places(root, images, skipped)


# ---- which cell encodes ------------------------------------------------------------------------------------

HDR_REFUSED = ("graphs.colour: hdr: the encoders of this study's graph cells read node colours of HDR radiance "
               "(color.hdf5), which a photo does not have, so no graph database is built from them.")
# the image methods whose cell learns what their descriptor needs (a vocabulary, weights): its model.pt
STATEFUL = ("orb_bow", "image_triplet", "imagenet_vlad", "imagenet_triplet")
TWIN_SUFFIX = "_tonemapped"


def _image_method(study: Study, method: str | None) -> bool:
    return method is not None and method in study.methods and methods.kind(method, study) == "image"


def _predicted(study: Study, scenario: str) -> bool:
    sc = study.scenarios.get(scenario)
    return sc is not None and sc.depth != "gt" and sc.semantic != "gt" and sc.depth_scale == 1.0


def _finished_cells(study: Study, method: str | None) -> list[tuple[dict, Path]]:
    """(record, folder) of the study's finished cells of `method` (None: every graph method) with a model.pt
    where the method learns one."""
    image = _image_method(study, method)
    wanted = [method] if method else study.graph_methods()
    out = []
    for m in wanted:
        for f in sorted((paths.study_dir(study.name) / "cells" / m).glob("*/cell.json")):
            if (not image or m in STATEFUL) and not (f.parent / "model.pt").is_file():
                continue
            out.append((read_json(f), f.parent))
    return out


def _best(found: list[tuple[dict, Path]]) -> tuple[dict, Path] | None:
    best = None
    for c, folder in found:
        if best is None or cell_metrics(c)[PAPER]["recall@1"] > cell_metrics(best[0])[PAPER]["recall@1"]:
            best = (c, folder)
    return best


def pick(study: Study, method: str | None = None, train: bool = True) -> tuple[Study, dict]:
    """(the study the cell belongs to, its record with its ``folder``) of the cell that makes the database: for an
    image method its best cell; for a graph method (`method`, or any) the best finished cell (``paper`` recall@1)
    whose scenario has predicted depth and semantics and tonemapped node colours, else, with `train`, the
    tonemapped twin of the best such cell of HDR colours (`tonemapped_twin`, trained once); without `train` that
    case is one `LocalizeError` (`HDR_REFUSED`)."""
    image = _image_method(study, method)
    if method is not None and not image and method not in study.graph_methods():
        known = study.graph_methods() + [m for m in study.methods if methods.kind(m, study) == "image"]
        raise LocalizeError(f"{study.path}: --method {method}: not a method of study {study.name}; expected one "
                            f"of {', '.join(known)}")
    found = _finished_cells(study, method)
    if image:
        best = _best(found)
    else:
        found = [(c, f) for c, f in found if _predicted(study, c["scenario"])]
        best = _best([(c, f) for c, f in found if study.colour(c["scenario"]) == "tonemapped"])
        hdr = _best([(c, f) for c, f in found if study.colour(c["scenario"]) != "tonemapped"])
        if best is None and hdr is not None:
            if not train:
                raise LocalizeError(f"{study.path}: {HDR_REFUSED}")
            return tonemapped_twin(study, {**hdr[0], "folder": str(hdr[1])})
    if best is None:
        what = (f"{method} cell" + (" with a saved model.pt" if method in STATEFUL else "") if image
                else f"{method or 'graph-method'} cell with predicted depth and semantics and a saved model.pt")
        raise LocalizeError(f"{paths.study_dir(study.name) / 'cells'}: no finished {what}; run "
                            f"`monolib study {study.name}` first")
    return study, {**best[0], "folder": str(best[1])}


def pick_cell(study: Study, method: str | None = None, train: bool = True) -> dict:
    """The record (with its ``folder``) of the cell `pick` chooses."""
    return pick(study, method, train)[1]


def twin_study(study: Study, scenario: str) -> tuple[Study, str]:
    """The study with one more scenario: `scenario`'s sources, depth scale and camera with tonemapped node colours,
    named ``<scenario>_tonemapped`` (``..._localizer`` when the study has a scenario of that name that differs)."""
    sc = study.scenarios[scenario]
    twin = dataclasses.replace(sc, colour="tonemapped", in_tables=False, thresholds=None,
                               projection=study.projection(scenario),
                               label=f"{sc.label}, tonemapped colours (the localizer's)")
    name = scenario + TWIN_SUFFIX
    have = study.scenarios.get(name)
    if have is not None and (have.depth, have.semantic, have.depth_scale, study.projection(name),
                             study.colour(name)) != (twin.depth, twin.semantic, twin.depth_scale, twin.projection,
                                                     "tonemapped"):
        name += "_localizer"
    return dataclasses.replace(study, scenarios={**study.scenarios, name: twin}), name


def twin_folder(study: Study, method: str, scenario: str, threshold: float, seed: int) -> Path:
    """Where a twin cell trained for the localizer lives: ``runs/<study>/localizer/cells/<method>/<name>/``."""
    return paths.study_dir(study.name) / "localizer" / "cells" / method / paths.cell_name(scenario, threshold, seed)


def tonemapped_twin(study: Study, hdr_cell: dict) -> tuple[Study, dict]:
    """(the twin study, the record of its cell) of the tonemapped twin of `hdr_cell` (a record with its
    ``folder``): the same method, threshold and seed on the scenario of `twin_study`, trained and evaluated by
    `monolib.retrieval.cell.run_cell` (its graphs built when missing, under the study's lock) unless a cell of the
    same key is in its folder already. The record names the cell it is the twin of (``twin_of``)."""
    twin, name = twin_study(study, hdr_cell["scenario"])
    method, seed = hdr_cell["method"], int(hdr_cell["seed"])
    threshold = float(hdr_cell["threshold"])  # "inf" reads as inf
    folder = twin_folder(study, method, name, threshold, seed)
    key = cells.cell_key(twin, method, name, threshold, seed)
    if cells.is_complete(folder, key):
        print(f"index: {method} cell {Path(hdr_cell['folder']).name} reads HDR node colours; using its tonemapped "
              f"twin, trained earlier ({folder})", flush=True)
    else:
        print(f"index: {method} cell {Path(hdr_cell['folder']).name} reads HDR node colours, which a photo does not "
              f"have; training its tonemapped twin once ({name}, threshold {paths.threshold_tag(threshold)} m, seed "
              f"{seed}; graphs of the tonemapped frames built when missing) into {folder} ...", flush=True)
        t = time.perf_counter()
        with locks.of_study(study):
            cells.run_cell(twin, method, name, threshold, seed, out_dir=str(folder))
        print(f"index: twin trained in {time.perf_counter() - t:.0f} s", flush=True)
    record = read_json(folder / "cell.json")
    return twin, {**record, "folder": str(folder), "twin_of": hdr_cell["folder"]}


# ---- the database ------------------------------------------------------------------------------------------

FORMAT = 2  # the database's layout; a database of another format is refused
META_KEYS = ("format", "study", "study_file", "cell", "method", "kind", "scenario", "threshold", "seed", "models",
             "encoder", "width", "height", "files", "code")
ROW_FILES = ("embeddings.npy", "frames.csv", "thumbnails.npy")
STATE_FILES = {"encoder": "encoder.pt", "semantic": "segmentation.pt", "depth": "depth.pt"}
THUMBNAIL = (128, 96)  # width, height of the copy of each database image that `--show` draws
# the stages whose code a query runs: a database made by other code of these is refused
QUERY_CODE = {"graph": ("perception", "graphs", "cells"), "image": ("features", "cells")}
DEFAULT_PROJECTION = "exact"


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


def thumbnail(rgb: np.ndarray) -> np.ndarray:
    """The `THUMBNAIL`-sized copy of an image (4:3, centre-cropped)."""
    return to_study_frame(rgb, *THUMBNAIL)


def _perception_files(study: Study, scenario: str) -> dict[str, tuple[str, Path]]:
    """``{role: (model name, its trained weights file)}`` of a scenario's networks; an untrained one is one error."""
    sc = study.scenarios[scenario]
    out = {}
    for role, name in (("semantic", sc.semantic), ("depth", sc.depth)):
        path = predictions.model_dir(study, name) / "model.pt"
        if not path.is_file():
            raise LocalizeError(f"{path}: model {name!r} is not trained; run `monolib perception "
                                f"{study.path or study.name}` first")
        out[role] = (name, path)
    return out


def _copy_file(source: Path, target: Path) -> str:
    """Copy `source` onto `target` atomically unless `target` holds the same bytes; its sha256."""
    digest = io.sha256(source)
    if not (target.is_file() and io.sha256(target) == digest):
        with atomic_path(target) as tmp:
            shutil.copyfile(source, tmp)
    return digest


def write_state(out: str | Path, study: Study, cell: dict, state: dict | torch.nn.Module,
                perception_files: dict[str, tuple[str, Path]] | None = None) -> dict:
    """Write what a query needs besides the database's rows into `out` (`encoder.pt`, and for a graph method
    copies of the perception weights: `perception_files`, default the study's trained models of the cell's
    scenario) and return the `meta.json` content without the rows' fields. `cell`: a cell record with its
    ``folder`` (and ``twin_of`` for a twin trained for the localizer)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    state = state.state_dict() if isinstance(state, torch.nn.Module) else state  # (an encoder: its weights)
    image = methods.kind(cell["method"], study) == "image"
    save_torch(out / STATE_FILES["encoder"], {k: v.detach().cpu() for k, v in state.items()})
    files = {STATE_FILES["encoder"]: io.sha256(out / STATE_FILES["encoder"])}
    models = {}
    if not image:
        for role, (name, path) in (perception_files or _perception_files(study, cell["scenario"])).items():
            files[STATE_FILES[role]] = _copy_file(Path(path), out / STATE_FILES[role])
            spec, task = predictions._spec(study, name)
            models[role] = {"name": name, "tag": predictions.model_tag(study, name), "task": task,
                            "spec": dataclasses.asdict(spec), "file": STATE_FILES[role]}
    kind = "image" if image else "graph"
    meta = {
        "format": FORMAT, "study": study.name, "study_file": study.path, "cell": cell["folder"],
        "twin_of": cell.get("twin_of"), "method": cell["method"], "kind": kind, "scenario": cell["scenario"],
        "threshold": cell["threshold"], "seed": cell["seed"], "cell_recall@1": cell_metrics(cell)[PAPER]["recall@1"],
        "models": models, "encoder": None if image else dataclasses.asdict(study.gcn_spec(cell["method"])),
        "width": study.dataset.width, "height": study.dataset.height,
        # the query graphs are built in the database's camera and colour space (an image method builds none)
        "projection": None if image else study.projection(cell["scenario"]),
        "colour": None if image else study.colour(cell["scenario"]),
        "files": files, "code": {s: versions.code_version(s) for s in QUERY_CODE[kind]},
        "libraries": {s: versions.library_versions(s) for s in QUERY_CODE[kind]},
    }
    # what decides an image's embedding: equal keys, reusable rows (`index_places`)
    meta["embedding_key"] = key_of({k: meta[k] for k in ("method", "kind", "threshold", "encoder", "width", "height",
                                                         "projection", "colour", "files", "code")})
    return meta


def write_rows(out: str | Path, meta: dict, frames: list[str], settings: list[str], embeddings: np.ndarray,
               thumbnails: np.ndarray | None = None, sha256: list[str] | None = None, **fields) -> Path:
    """The rows (`embeddings.npy`, `frames.csv`, `thumbnails.npy`), then `meta.json` with `fields` (written last)."""
    out = Path(out)
    with atomic_path(out / "embeddings.npy") as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(embeddings, np.float32))
    table = pd.DataFrame({"frame": frames, "setting": settings, "sha256": sha256 or [""] * len(frames)})
    write_text(out / "frames.csv", table.to_csv(index=False))
    if thumbnails is None:  # (a database written without images: grey)
        thumbnails = np.full((len(frames), THUMBNAIL[1], THUMBNAIL[0], 3), 128, np.uint8)
    with atomic_path(out / "thumbnails.npy") as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.asarray(thumbnails, np.uint8))
    write_json(out / "meta.json", {**meta, "frames": len(frames), "places_count": len(set(settings)), **fields})
    return out


def write_database(out: str | Path, study: Study, cell: dict, state: dict | torch.nn.Module, frames: list[str],
                   settings: list[str], embeddings: np.ndarray, thumbnails: np.ndarray | None = None,
                   perception_files: dict[str, tuple[str, Path]] | None = None) -> Path:
    """A whole database: `write_state`, then `write_rows` (one row per frame of `frames`, in `settings`)."""
    meta = write_state(out, study, cell, state, perception_files)
    return write_rows(out, meta, frames, settings, embeddings, thumbnails, places=None, skipped=[])


def build_index(study: Study, out: str | Path, method: str | None = None, places: str | Path | None = None) -> Path:
    """Write the database of the study's test frames (each setting a place), or of the images of `places`
    (`index_places`), into `out`, with the cell `pick` chooses."""
    out = Path(out)
    scanned = scan_places(places) if places is not None else None  # a bad folder: an error before any work
    s, c = pick(study, method)
    image = methods.kind(c["method"], s) == "image"
    state_file = Path(c["folder"]) / "model.pt"
    state = torch.load(state_file, map_location="cpu", weights_only=True) if state_file.is_file() else {}
    meta = write_state(out, s, c, state)
    if scanned is not None:
        return index_places(out, meta, scanned)
    test = selection.select_frames(s, dataset.open_dataset(s), s.gcn.val_settings).test
    if image:
        emb = describe_frames(image_describer(c["method"], state), test)
        keys, settings = [f.key for f in test], [f.setting for f in test]
    else:
        spec = s.gcn_spec(c["method"])
        model = gcn.GraphEncoder(spec)
        model.load_state_dict(state)
        model.to(device())
        graphs = [gcn.encoder_graph(g, float(c["threshold"]), spec, s.projection(c["scenario"]))
                  for g in scenegraphs.load(s, c["scenario"])["test"]]
        emb = gcn.embed(model, graphs).numpy().astype(np.float32)
        keys, settings = [g.frame for g in graphs], [g.setting for g in graphs]
    by_key = {f.key: f for f in test}
    thumbs = np.stack([thumbnail(by_key[k].rgb) for k in keys]) if keys else None
    return write_rows(out, meta, keys, settings, emb, thumbs, places=None, skipped=[])


def _previous_rows(out: Path, meta: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{sha256: (embedding, thumbnail)}`` of a database already in `out` made with the same `embedding_key`."""
    try:
        old, frames, emb = read_database(out)
        thumbs = np.load(out / "thumbnails.npy")
    except (LocalizeError, OSError, ValueError):
        return {}
    if old.get("embedding_key") != meta["embedding_key"] or "sha256" not in frames or len(thumbs) != len(emb):
        return {}
    return {h: (emb[i], thumbs[i]) for i, h in enumerate(frames["sha256"].fillna("").astype(str)) if h}


def index_places(out: Path, meta: dict, places: Places) -> Path:
    """Embed the images of `places` into the database whose state `write_state` wrote into `out` (an image whose
    content the previous database in `out` held for the same `embedding_key` is not embedded again)."""
    previous = _previous_rows(out, meta)
    loc = Localizer.load(out, meta)
    rows, new = [], 0
    for place, files in places.images.items():
        for rel in files:
            path = places.root / rel
            digest = io.sha256(path) if path.is_file() else ""
            if digest in previous:
                z, thumb = previous[digest]
            else:
                rgb = loc.read(path)
                z, thumb = loc.stages(rgb).numpy(), thumbnail(rgb)
                new += 1
            rows.append((rel, place, digest, z, thumb))
    n = len(rows)
    print(f"index: {n} images of {len(places.images)} places in {places.root}: {new} embedded, {n - new} unchanged "
          f"(kept from the database)" + (f"; skipped {len(places.skipped)}: " + "; ".join(places.skipped)
                                         if places.skipped else ""), flush=True)
    return write_rows(out, meta, [r[0] for r in rows], [r[1] for r in rows], np.stack([r[3] for r in rows]),
                      np.stack([r[4] for r in rows]), [r[2] for r in rows], places=str(places.root.resolve()),
                      skipped=places.skipped, embedded=new)


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
    if isinstance(meta, dict) and meta.get("format", 1) != FORMAT:
        raise LocalizeError(f"{db / 'meta.json'}: a database of format {meta.get('format', 1)}; this installation "
                            f"reads format {FORMAT}; rebuild it with `monolib index {meta.get('study', 'STUDY')} "
                            f"--out {db}`")
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
    frames["setting"] = frames["setting"].astype(str)
    return meta, frames, emb


def check_database(db: Path, meta: dict) -> None:
    """One `LocalizeError` unless the state files are those `meta` names (sha256) and the code of the stages a
    query runs is this installation's."""
    rebuild = f"rebuild it with `monolib index {meta['study']} --out {db}`"
    for name, digest in meta["files"].items():
        if not (db / name).is_file():
            raise LocalizeError(f"{db / name}: missing; {rebuild}")
        now = io.sha256(db / name)
        if now != digest:
            role = next((r for r, f in STATE_FILES.items() if f == name), name)
            raise LocalizeError(f"{db / name}: sha256 {now[:12]}, but meta.json records {digest[:12]} for the "
                                f"{role} state: the database was made by other models than those it holds; {rebuild}")
    for stage, version in meta["code"].items():
        if version != versions.code_version(stage):
            raise LocalizeError(f"{db / 'meta.json'}: made by other code: its {stage} code version {version}, this "
                                f"installation's {versions.code_version(stage)}; {rebuild}")
    if meta["kind"] == "graph" and meta.get("colour") != "tonemapped":
        raise LocalizeError(f"{db / 'meta.json'}: {HDR_REFUSED}")


def _load_network(db: Path, model: dict, prepare: bool = True):
    spec_type = SegmentationSpec if model["task"] == "segmentation" else DepthSpec
    spec = spec_type(**model["spec"])
    if model["task"] == "segmentation":
        net = seg_mod.for_inference(seg_mod.load_model(spec, db / model["file"])).eval()
    else:
        net = depth_mod.load_model(spec, db / model["file"]).eval()
    return prepare_network(net) if prepare else net


@dataclass
class Localizer:
    db: Path
    meta: dict
    segmentation: torch.nn.Module | None
    depth: torch.nn.Module | None
    encoder: gcn.GraphEncoder | None
    embeddings: torch.Tensor
    frames: pd.DataFrame
    describe: object = None  # an image method's descriptor function (`image_describer`); None for a graph method

    def __post_init__(self):
        settings = self.frames["setting"]
        self._place_codes = pd.factorize(settings)[0] if len(settings) else np.zeros(0, np.int64)
        self._places = settings.tolist()
        self._images = self.frames["frame"].tolist()

    @staticmethod
    def open(db: str | Path, prepare: bool = True) -> "Localizer":
        """The localizer of a database folder (`read_database`, `check_database`), its networks loaded (`prepare`:
        prepared for queries, `prepare_network`)."""
        db = Path(db)
        meta, frames, emb = read_database(db)
        return Localizer.load(db, meta, frames, emb, prepare)

    @staticmethod
    def load(db: str | Path, meta: dict, frames: pd.DataFrame | None = None,
             emb: np.ndarray | None = None, prepare: bool = True) -> "Localizer":
        """The localizer of the state files in `db` that `meta` names (rows: `frames`, `emb`; none while indexing);
        `prepare`: its perception networks prepared for queries (`prepare_network`), else as `monolib perception`
        loads them."""
        db = Path(db)
        check_database(db, meta)
        frames = frames if frames is not None else pd.DataFrame({"frame": [], "setting": []})
        emb_t = torch.from_numpy(emb if emb is not None else np.zeros((0, 1), np.float32))
        state = torch.load(db / STATE_FILES["encoder"], map_location="cpu", weights_only=True)
        if meta["kind"] == "image":
            return Localizer(db, meta, None, None, None, emb_t, frames, image_describer(meta["method"], state))
        try:
            seg, dep = (_load_network(db, meta["models"][r], prepare) for r in ("semantic", "depth"))
            encoder = gcn.GraphEncoder(GCNSpec(**meta["encoder"]))
            encoder.load_state_dict(state)
        except (TypeError, KeyError, RuntimeError) as exc:
            raise LocalizeError(f"{db / 'meta.json'}: its models do not load in this installation ({exc}); rebuild "
                                f"it with `monolib index {meta['study']} --out {db}`") from None
        encoder.to(device()).eval()  # the networks run on the GPU when there is one; embeddings come back on the CPU
        return Localizer(db, meta, seg, dep, encoder, emb_t, frames)

    def read(self, path: str | Path) -> np.ndarray:
        """`read_image` at a scale that keeps the study's resolution."""
        return read_image(path, DECODE_SCALE * max(self.meta["width"], self.meta["height"]))

    def analyse(self, rgb: np.ndarray, timings: dict | None = None, drawn: bool = True) -> dict:
        """The per-image pipeline: ``frame`` (the image at the study's size), and for a graph database
        ``semantic``, ``depth``, ``nodes`` (NYU40 ids), and with `drawn` what `query_figure` draws besides:
        ``pixels`` (each node's median image column and row) and ``edges`` (node index pairs closer than the
        threshold); ``embedding`` (D,) on the CPU."""
        t = time.perf_counter()
        w, h = self.meta["width"], self.meta["height"]
        frame = to_study_frame(rgb, w, h)
        if self.describe is not None:  # an image method: its descriptor is the whole pipeline
            z = torch.from_numpy(self.describe(frame[None])[0])
            if timings is not None:
                timings.setdefault("descriptor", []).append(time.perf_counter() - t)
            return {"frame": frame, "embedding": z}
        semantic = seg_mod.predict(self.segmentation, frame[None])[0]
        t1 = time.perf_counter()
        depth = depth_mod.predict(self.depth, frame[None])[0]
        t2 = time.perf_counter()
        projection = self.meta.get("projection") or DEFAULT_PROJECTION
        x, pos = scene_nodes(frame, depth, semantic, Camera.canonical(w, h), projection)
        threshold = float(self.meta["threshold"])  # "inf" reads as inf
        g = graph.complete_graph(x, pos, "query", "query")
        z_graph = gcn.encoder_graph(g, threshold, self.encoder.spec, projection)
        t3 = time.perf_counter()
        z = gcn.embed(self.encoder, [z_graph])[0]
        t4 = time.perf_counter()
        if timings is not None:
            for k, v in (("segmentation", t1 - t), ("depth", t2 - t1), ("graph", t3 - t2), ("encoder", t4 - t3)):
                timings.setdefault(k, []).append(v)
        seen = {"frame": frame, "semantic": semantic, "depth": depth, "nodes": x[:, 0].astype(int), "embedding": z}
        if drawn:  # (the pixels' medians cost as much as the graph's positions: only for a figure)
            keep = pair_mask(g.pair_len, threshold)
            seen.update(pixels=node_pixels(depth, semantic), edges=g.pair_index[:, keep].T.numpy())
        return seen

    def stages(self, rgb: np.ndarray, timings: dict | None = None) -> torch.Tensor:
        """The (D,) embedding of an image (`analyse`, without what only a figure draws)."""
        return self.analyse(rgb, timings, drawn=False)["embedding"]

    def rank(self, z: torch.Tensor, k: int) -> list[dict]:
        """The k nearest places of an embedding, each by its closest database image (ties of distance: the
        earlier row)."""
        d = torch.cdist(z[None].float(), self.embeddings.float())[0].numpy()
        order = np.argsort(d, kind="stable")
        _, first = np.unique(self._place_codes[order], return_index=True)  # each place's first row in `order`
        rows = order[np.sort(first)[:k]]
        root = self.meta.get("places")
        return [{"rank": i + 1, "place": self._places[r], "distance": float(d[r]), "image": self._images[r],
                 **({"path": str(Path(root) / self._images[r])} if root else {}), "row": int(r)}
                for i, r in enumerate(rows)]

    def query(self, rgb: np.ndarray, k: int = 5) -> list[dict]:
        """The k nearest places (`rank`) of an image."""
        return [{k_: v for k_, v in m.items() if k_ != "row"} for m in self.rank(self.stages(rgb), k)]


def node_pixels(depth: np.ndarray, semantic: np.ndarray) -> np.ndarray:
    """(L, 2) median image column and row of each node's pixels, in the nodes' order (`scene_nodes`: the labelled
    pixels of finite positive depth, labels ascending)."""
    h, w = semantic.shape
    with np.errstate(invalid="ignore"):
        valid = ((semantic >= 1) & np.isfinite(depth) & (depth > 0)).reshape(-1)
    idx = np.flatnonzero(valid)
    cols, rows = idx % w, idx // w
    return grouped_median(semantic.reshape(-1)[idx], np.stack([cols, rows]).astype(np.float64))[1]


DEFAULT_K = 5


SHOW_SUFFIXES = (".png", ".pdf", ".svg")


def _queries(images: list[str], db: str | Path, k: int | None, drawn: bool = True):
    """(image path, localizer, `Localizer.analyse` of it (`drawn`: with what a figure draws), `Localizer.rank` of
    it) of each image."""
    if k is not None and k < 1:
        raise LocalizeError(f"--k {k}: expected at least 1 (the number of nearest places to list)")
    _, frames, _ = read_database(db)
    n = int(frames["setting"].nunique())
    if k is None:
        k = min(DEFAULT_K, n)
    elif k > n:
        raise LocalizeError(f"--k {k}: the database {db} holds {n} places; expected 1 to {n}")
    loc = Localizer.open(db)
    rgbs = [loc.read(p) for p in images]  # every path checked before any work
    for p, rgb in zip(images, rgbs):
        seen = loc.analyse(rgb, drawn=drawn)
        yield p, loc, seen, loc.rank(seen["embedding"], k)


def localize(images: list[str], db: str | Path, k: int | None = None, show: str | Path | None = None) -> list[dict]:
    """The `k` nearest places of each image (default: `DEFAULT_K`, or every place of a smaller database); `show`:
    also draw each query's figure there (`query_figure`; several images: ``OUT-1.png``, ``OUT-2.png``, ...).

    A `k` given must be 1 .. the number of places in the database, else one `LocalizeError` before any model is
    loaded. A larger one is an error, not clamped: the localizer ranks places (each by its closest image), so it
    cannot list more than the database holds, and a clamp would silently print fewer matches than asked (a script
    reading ``--json`` would get fewer rows than it asked for); the error says the largest k the database allows."""
    if show is not None and Path(show).suffix.lower() not in SHOW_SUFFIXES:
        raise LocalizeError(f"--show {show}: expected a file name ending in {', '.join(SHOW_SUFFIXES)}")
    out = []
    for i, (p, loc, seen, matches) in enumerate(_queries(images, db, k, drawn=show is not None)):
        result = {"image": str(p), "matches": [{k_: v for k_, v in m.items() if k_ != "row"} for m in matches]}
        if show is not None:
            show = Path(show)
            target = show if len(images) == 1 else show.with_name(f"{show.stem}-{i + 1}{show.suffix}")
            io.save_figure(query_figure(loc, seen, matches, Path(p).name), target)
            result["figure"] = str(target)
        out.append(result)
    return out


def query_figures(images: list[str], db: str | Path, k: int | None = None) -> list:
    """The figure (`query_figure`) of each image, for a notebook to show."""
    return [query_figure(loc, seen, matches, Path(p).name) for p, loc, seen, matches in _queries(images, db, k)]


def figure_png(fig) -> bytes:
    """A figure's PNG bytes (for `IPython.display.Image`: shown whatever the notebook's matplotlib backend)."""
    import io as bytes_io

    buffer = bytes_io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    return buffer.getvalue()


def format_results(results: list[dict]) -> str:
    lines = []
    for r in results:
        lines.append(r["image"])
        lines += [f"  {m['rank']}. {m['place']}  distance {m['distance']:.3f}  (closest image {m['image']})"
                  for m in r["matches"]]
        if "figure" in r:
            lines.append(f"  figure: {r['figure']}")
    return "\n".join(lines)


def describe_database(db: str | Path) -> str:
    """The line `monolib index` prints: method, cell (and the cell it is the twin of), colour space, rows."""
    meta, frames, _ = read_database(db)
    what = (f"{meta['method']} ({meta['kind']} method)" if meta["kind"] == "image" else
            f"{meta['method']}, scenario {meta['scenario']} at {paths.threshold_tag(float(meta['threshold']))} m, "
            f"node colours {meta['colour']}")
    twin = f", trained for the localizer as the tonemapped twin of {meta['twin_of']}" if meta.get("twin_of") else ""
    source = f"the places of {meta['places']}" if meta.get("places") else f"the test frames of study {meta['study']}"
    return (f"database: {db}: {what}; cell {meta['cell']}{twin} (paper recall@1 {meta['cell_recall@1']:.1f}); "
            f"{len(frames)} images of {frames['setting'].nunique()} places, {source}")


# ---- what it saw -------------------------------------------------------------------------------------------

def query_figure(loc: Localizer, seen: dict, matches: list[dict], title: str = "query"):
    """A matplotlib `Figure` of a query (no pyplot: a notebook's backend is left as it is): the image at the
    study's size, its predicted semantics and depth, its scene graph over the image (each node at the median pixel
    of its object, labelled, each edge of the database's threshold a line), and its nearest places, each with its
    closest database image."""
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure

    thumbs = np.load(loc.db / "thumbnails.npy", mmap_mode="r") if (loc.db / "thumbnails.npy").is_file() else None
    cols = max(4, len(matches))
    fig = Figure(figsize=(3.2 * cols, 5.8))
    axes = fig.subplots(2, cols, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    frame = seen["frame"]
    axes[0, 0].imshow(frame)
    axes[0, 0].set_title(title, fontsize=9)
    if "semantic" in seen:
        axes[0, 1].imshow(nyu40.colourize(seen["semantic"]))
        axes[0, 1].set_title("predicted semantics (NYU40)", fontsize=9)
        im = axes[0, 2].imshow(seen["depth"], cmap="viridis")
        fig.colorbar(im, ax=axes[0, 2], fraction=0.046, pad=0.02, label="m")
        axes[0, 2].set_title("predicted depth", fontsize=9)
        ax = axes[0, 3]
        ax.imshow(frame, alpha=0.6)
        px = seen["pixels"]
        if len(seen["edges"]):
            ax.add_collection(LineCollection(px[seen["edges"]], colors="white", linewidths=1.0, alpha=0.9))
        ax.scatter(px[:, 0], px[:, 1], s=28, c="red", edgecolors="white", linewidths=0.8, zorder=3)
        for (u, v), label in zip(px, seen["nodes"]):
            ax.annotate(nyu40.name(int(label)), (u, v), fontsize=6, color="yellow", xytext=(3, 3),
                        textcoords="offset points")
        ax.set_xlim(0, frame.shape[1])
        ax.set_ylim(frame.shape[0], 0)
        ax.set_title(f"scene graph: {len(px)} nodes, {len(seen['edges'])} edges "
                     f"(threshold {paths.threshold_tag(float(loc.meta['threshold']))} m)", fontsize=9)
    else:
        axes[0, 1].text(0.5, 0.5, f"{loc.meta['method']}: an image method\n(no semantics, depth or graph)",
                        ha="center", va="center", fontsize=9, transform=axes[0, 1].transAxes)
    for i, m in enumerate(matches):
        ax = axes[1, i]
        if thumbs is not None and m["row"] < len(thumbs):
            ax.imshow(np.asarray(thumbs[m["row"]]))
        ax.set_title(f"{m['rank']}. {m['place']}\ndistance {m['distance']:.3f}\n{m['image']}",
                     fontsize=8)
    fig.suptitle(f"{loc.meta['method']} ({loc.meta['kind']} method): the nearest places in {loc.db.name}",
                 fontsize=10)
    fig.tight_layout()
    return fig


# ---- example photos ----------------------------------------------------------------------------------------

def write_jpeg(rgb: np.ndarray, path: str | Path, quality: int = 90) -> Path:
    """An (H, W, 3) uint8 RGB image written as a JPEG file of `quality` (OpenCV's encoder), atomically."""
    ok, data = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise LocalizeError(f"{path}: the image did not encode as JPEG")
    with atomic_path(Path(path)) as tmp:
        tmp.write_bytes(data.tobytes())
    return Path(path)


def example_photos(study: Study, folder: str | Path, quality: int = 90) -> tuple[Path, list[Path]]:
    """JPEG "photos" (quality `quality`) of the study's test settings, as a user would take them: the first test
    frame of each setting in ``folder/places/<setting>/``, a frame from the middle of the setting's frames as
    ``folder/queries/<setting>.jpg``. Returns (the places folder, the query files)."""
    folder = Path(folder)
    test = selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings).test
    by_setting: dict[str, list] = {}
    for f in test:
        by_setting.setdefault(f.setting, []).append(f)
    queries = []
    for setting, frames in sorted(by_setting.items()):
        for f, path in ((frames[0], folder / "places" / setting / f"{frames[0].key.replace('/', '_')}.jpg"),
                        (frames[len(frames) // 2], folder / "queries" / f"{setting}.jpg")):
            write_jpeg(f.rgb, path, quality)
        queries.append(folder / "queries" / f"{setting}.jpg")
    return folder / "places", queries


def ensure_cell(study: Study | str, method: str | None = None) -> Study:
    """The study, with a cell `build_index` can read: when the study has no finished cell of a predicted-input
    scenario (a fresh clone), its first such scenario is prepared (`monolib.study.runner.prepare`) and its cell at
    the study's smallest threshold and first seed run, as the grid would run it."""
    from monolib.study.runner import prepare  # deferred: the runner's notebook and cluster machinery

    study = load_study(study) if isinstance(study, str) else study
    if _image_method(study, method) or [c for c, _ in _finished_cells(study, method)
                                        if _predicted(study, c["scenario"])]:
        return study
    scenario = next((n for n in study.scenarios if _predicted(study, n) and study.colour(n) == "tonemapped"),
                    next((n for n in study.scenarios if _predicted(study, n)), None))
    if scenario is None:
        raise LocalizeError(f"{study.path}: no scenario with predicted depth and semantics; expected one for the "
                            f"localizer")
    study = prepare(study, [scenario])
    with locks.of_study(study):
        cells.run_cell(study, method or study.graph_methods()[0], scenario, min(study.thresholds), study.seeds[0])
    return study
