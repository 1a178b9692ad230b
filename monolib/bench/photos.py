"""`monolib bench localize` (`make bench-localize`, figures/localize.md and .csv): recall@1 of the localizer of
each method it offers when the frames of the study's test settings go through the photo path (JPEG, decoded,
centre-cropped and resized), beside the same cells' recall@1 on the study's own frames; and one image's latency
end to end on one torch thread, median and p90."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from monolib import io, localize, methods, paths
from monolib.data import selection
from monolib.data import dataset
from monolib.device import cpu_signature
from monolib.localize import Localizer
from monolib.params import PAPER, load_study
from monolib.report.results import cell_metrics
from monolib.retrieval import evaluate
from monolib.retrieval.metrics import metrics_from_hits

LATENCY_GOAL_MS = 50.0  # what one image through a graph method should take end to end, on one thread


PHONE_PHOTO = (4032, 3024)  # a 12-megapixel photo's width and height: what reading a camera's JPEG costs


LATENCY_STAGES = ("read", "segmentation", "depth", "graph", "encoder", "descriptor", "knn")  # a query's stages


def _recall_at_1(emb: np.ndarray, draw: evaluate.Draw, protocol) -> float:
    """A cell's ``paper`` recall@1 of `emb` (rows in `draw`'s order): `evaluate.rank` and `metrics_from_hits`, as
    `evaluate.evaluate` scores a cell (a query's candidates: its setting's positives and every frame of the other
    settings)."""
    q, idx, _ = evaluate.rank(emb, draw, evaluate.ranking_depth(protocol))
    hits = draw.settings[idx] == draw.settings[q][:, None]
    return metrics_from_hits(hits, protocol.recall_k, protocol.precision_k)["recall@1"]


def _places_recall_at_1(loc: Localizer, emb: np.ndarray, draw: evaluate.Draw) -> float:
    """Recall@1 of a database of the positives alone (each setting a place, as `--places` makes one): each query's
    nearest place by `Localizer.rank`."""
    pos = ~draw.is_query
    frames = np.asarray(draw.frames)
    db = dataclasses.replace(loc, embeddings=torch.from_numpy(np.ascontiguousarray(emb[pos])),
                             frames=pd.DataFrame({"frame": frames[pos], "setting": draw.settings[pos]}))
    hits = [db.rank(torch.from_numpy(emb[i]), 1)[0]["place"] == draw.settings[i] for i in np.flatnonzero(draw.is_query)]
    return float(100.0 * np.mean(hits))


def localize_photos(study_name: str = "quick", out: str | Path | None = None, latency_images: int = 100,
                    quality: int = 90) -> dict:
    """Recall@1 and latency of the localizer on photos: per method it offers (the default graph database's, then
    each image method of the study), `monolib index STUDY --method M` into a temporary database, then every frame
    of the ``paper`` protocol's test settings through the photo path: its tonemapped RGB written as a JPEG of
    `quality` (`localize.write_jpeg`, as `example_photos` writes them), decoded by `Localizer.read`
    (`read_image`), then `Localizer.stages` (centre-crop and resize, perception, graph, encoder; an image method's
    descriptor) and `Localizer.rank` over the database, on one torch thread (and one OpenCV thread).

    Recall@1 is scored on the database cell's own draw (its ``protocol.csv``: which frames are queries, which
    positives), as the cell scores its embeddings (`_recall_at_1`), beside the cell's own ``paper`` recall@1 on
    the study's frames (`cell.json`); and on a database of the positives alone, ranked by `Localizer.rank`
    (`_places_recall_at_1`), on the study's frames (the database's rows) and on the photos. Latency: each image
    end to end (read, stages, rank), the first untimed (a warm-up), at least `latency_images` images per method
    (the frames again, in order, when the protocol holds fewer). With `out` (a ``.md``), also that page and a CSV
    of the same numbers beside it (`localize_page`, `localize_table`). The recall numbers are deterministic, the
    timings are not."""
    import os
    import tempfile

    import cv2

    start = time.perf_counter()
    study = load_study(study_name)
    old_threads, old_cv = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    record = {"study": study.name, "cpu": cpu_signature(), "cores": os.cpu_count(), "torch_threads": 1,
              "date": time.strftime("%Y-%m-%d"), "load_average_start": round(os.getloadavg()[0], 2),
              "jpeg_quality": quality, "width": study.dataset.width, "height": study.dataset.height,
              "latency_goal_ms": LATENCY_GOAL_MS, "methods": []}
    offered = [None] + [m for m in study.methods if methods.kind(m, study) == "image"]
    print(f"localize bench, study {study.name}: {len(offered)} methods, photos as JPEG quality {quality}, one torch "
          f"thread; {record['cpu']}, {record['cores']} cores, load average {record['load_average_start']}",
          flush=True)
    test = {f.key: f for f in selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings).test}
    try:
        with tempfile.TemporaryDirectory(prefix="monolib-localize-") as tmp:
            photos: dict[str, Path] = {}
            for method in offered:
                t = time.perf_counter()
                db = localize.build_index(study, Path(tmp) / f"db-{method or 'graph'}", method)
                meta, table, emb = localize.read_database(db)
                loc = Localizer.open(db)
                row = _photo_path_row(study, loc, meta, table, emb, test, photos, Path(tmp) / "photos", quality,
                                      latency_images, default=method is None)
                if "read_phone_photo_ms" not in record:
                    record.update(_phone_photo_read(loc, test[row["first_frame"]], Path(tmp), quality))
                row.pop("first_frame")
                row["seconds"] = round(time.perf_counter() - t, 1)
                record["methods"].append(row)
                print(f"  {row['method']:<14} recall@1: study's frames {row['recall@1_study']:.1f} (cell.json), "
                      f"photos {row['recall@1_photo']:.1f}; places database: {row['recall@1_places_study']:.1f} / "
                      f"{row['recall@1_places_photo']:.1f}; {row['queries']} queries; latency median "
                      f"{row['latency_median_ms']:.1f} ms, p90 {row['latency_p90_ms']:.1f} ms over "
                      f"{row['latency_images']} images ({row['seconds']:.0f} s)", flush=True)
    finally:
        torch.set_num_threads(old_threads)
        cv2.setNumThreads(old_cv)
    record["load_average_end"] = round(os.getloadavg()[0], 2)
    record["seconds"] = round(time.perf_counter() - start)
    if out:
        out = Path(out)
        io.write_text(out, localize_page(record))
        io.write_text(out.with_suffix(".csv"), localize_table(record).to_csv(index=False))
        print(f"written: {out} and {out.with_suffix('.csv')}")
    return record


def _photo_path_row(study, loc: Localizer, meta: dict, table: pd.DataFrame, emb: np.ndarray, test: dict,
                    photos: dict, folder: Path, quality: int, latency_images: int, default: bool) -> dict:
    """One method's row of `localize_photos` (its database open in `loc`; `photos`: the JPEGs written so far)."""
    cell_dir = Path(meta["cell"])
    cell = io.read_json(cell_dir / "cell.json")
    drawn = pd.read_csv(cell_dir / "protocol.csv", dtype=str)
    drawn = drawn[drawn["protocol"] == PAPER]
    keys = drawn["frame"].tolist()
    draw = evaluate.Draw(keys, drawn["setting"].to_numpy(), (drawn["role"] == "query").to_numpy())
    for key in keys:
        if key not in photos:
            photos[key] = localize.write_jpeg(test[key].rgb, folder / f"{key.replace('/', '_')}.jpg", quality)
    k = min(localize.DEFAULT_K, int(loc.frames["setting"].nunique()))
    loc.rank(loc.stages(loc.read(photos[keys[0]])), k)  # warm-up, untimed
    timings: dict = {}
    seconds, rows = [], {}
    timed = keys + [keys[i % len(keys)] for i in range(max(0, latency_images - len(keys)))]
    for i, key in enumerate(timed):
        t = time.perf_counter()
        rgb = loc.read(photos[key])
        t1 = time.perf_counter()
        z = loc.stages(rgb, timings)
        t2 = time.perf_counter()
        loc.rank(z, k)
        t3 = time.perf_counter()
        timings.setdefault("read", []).append(t1 - t)
        timings.setdefault("knn", []).append(t3 - t2)
        seconds.append(t3 - t)
        if i < len(keys):
            rows[key] = z.numpy()
    photo = np.stack([rows[key] for key in keys]).astype(np.float32)
    at = {f: i for i, f in enumerate(table["frame"].astype(str))}
    study_rows = emb[[at[key] for key in keys]].astype(np.float32)  # the database's rows: the study's own frames
    ms = 1000 * np.asarray(seconds)
    return {
        "method": meta["method"], "kind": meta["kind"], "default": default,
        "cell": _repo_path(cell_dir), "twin_of": Path(meta["twin_of"]).name if meta.get("twin_of") else "",
        "scenario": meta["scenario"], "threshold": meta["threshold"], "seed": int(meta["seed"]),
        "colour": meta.get("colour") or "", "database_frames": int(len(table)),
        "settings": int(len(set(draw.settings))), "queries": int(draw.is_query.sum()),
        "positives": int((~draw.is_query).sum()), "draw_seed": int(cell["protocols"][PAPER]["draw_seed"]),
        "recall@1_study": round(float(cell_metrics(cell)[PAPER]["recall@1"]), 2),
        "recall@1_study_rescored": round(_recall_at_1(study_rows, draw, study.protocol), 2),
        "recall@1_photo": round(_recall_at_1(photo, draw, study.protocol), 2),
        "recall@1_places_study": round(_places_recall_at_1(loc, study_rows, draw), 2),
        "recall@1_places_photo": round(_places_recall_at_1(loc, photo, draw), 2),
        "latency_images": len(ms), "latency_median_ms": round(float(np.median(ms)), 1),
        "latency_p90_ms": round(float(np.percentile(ms, 90)), 1),
        **{f"{s}_median_ms": round(1000 * float(np.median(timings[s])), 2) if s in timings else None
           for s in LATENCY_STAGES},
        "first_frame": keys[0],
    }


def _phone_photo_read(loc: Localizer, frame, folder: Path, quality: int, repeat: int = 10) -> dict:
    """Milliseconds to read a `PHONE_PHOTO`-sized JPEG (a study frame enlarged) and bring it to the study's size,
    beside the same for the frame's own JPEG (median of `repeat`, after one untimed read each)."""
    import cv2

    w, h = loc.meta["width"], loc.meta["height"]
    out = {}
    for name, rgb in (("read_study_photo_ms", frame.rgb),
                      ("read_phone_photo_ms", cv2.resize(frame.rgb, PHONE_PHOTO, interpolation=cv2.INTER_LINEAR))):
        path = localize.write_jpeg(rgb, folder / f"{name}.jpg", quality)
        localize.to_study_frame(loc.read(path), w, h)
        times = []
        for _ in range(repeat):
            t = time.perf_counter()
            localize.to_study_frame(loc.read(path), w, h)
            times.append(time.perf_counter() - t)
        out[name] = round(1000 * float(np.median(times)), 1)
    return out


def _repo_path(path: Path) -> str:
    """`path` relative to the checkout when it is inside it (a figure names no machine's folders)."""
    try:
        return str(Path(path).resolve().relative_to(paths.ROOT.resolve()))
    except ValueError:
        return Path(path).name


def localize_table(record: dict) -> pd.DataFrame:
    """`localize_photos`' numbers, one row per method (the CSV beside the page)."""
    keep = ("study", "cpu", "cores", "torch_threads", "date", "jpeg_quality")
    return pd.DataFrame([{**{k: record[k] for k in keep}, **row} for row in record["methods"]])


def localize_page(record: dict) -> str:
    """The Markdown page of `localize_photos`' record (figures/localize.md)."""
    rows = record["methods"]
    first = rows[0] if rows else {}
    w, h = record["width"], record["height"]
    same_draw = len({r["draw_seed"] for r in rows}) == 1
    lines = [
        "# Localizing photos: recall@1 and latency", "",
        f"`monolib bench localize --study {record['study']}` (`make bench-localize` for `quick`), "
        f"{record['date']}, on {record['cpu']}, {record['cores']} cores, {record['torch_threads']} torch thread "
        f"(and one OpenCV thread); load average {record['load_average_start']} at the start and "
        f"{record['load_average_end']} at the end (the bench itself counts about 1; the rest is other processes "
        f"on the same cores). The whole bench took {record['seconds']} s.", "",
        "## Recall@1: the study's frames against the same frames as photos", "",
        f"Per method the localizer offers, the database `monolib index {record['study']} --method M` writes (the "
        f"first row: the default database, `monolib index {record['study']}`) and the cell it is made from. The "
        f"photo path: each frame of the `paper` protocol's {first.get('settings', 0)} test settings "
        f"({first.get('queries', 0) + first.get('positives', 0)} frames), its tonemapped RGB written as a JPEG of "
        f"quality {record['jpeg_quality']}, decoded by `read_image`, centre-cropped to 4:3 and resized to "
        f"{w} x {h} as a photo is, and embedded by the `Localizer` a user's query runs through (for a graph method "
        f"its segmentation, depth, scene graph and encoder; for an image method its descriptor). The queries are "
        f"the cell's own draw of the `paper` protocol (its `protocol.csv`: per setting "
        f"{first.get('queries', 0) // max(first.get('settings', 1), 1)} queries and "
        f"{first.get('positives', 0) // max(first.get('settings', 1), 1)} positives; "
        + ("the same draw for every method" if same_draw else "each cell's seed draws its own") + ").", "",
        "- **study's frames**: the cell's `paper` recall@1 in its `cell.json`, from the embeddings of the frames as "
        "the study made them (a graph method: the graphs of its scenario's perception stage);",
        "- **photos**: the same score of the photos' embeddings, each query ranked against its setting's positives "
        "and every frame of the other settings (all photos), as the cell scores its own;",
        "- **places, study's frames / photos**: a database of the positives alone, each setting a place (what "
        "`monolib index --places` makes of a few images per place), each query's nearest place by `Localizer.rank`; "
        "the database and the queries both from the study's frames (the database's own rows), or both photos.", "",
        "| method | cell | queries | recall@1, study's frames | recall@1, photos | photos - study's frames | "
        "places: study's frames | places: photos |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        what = f"`{r['method']}`" + (" (default database)" if r["default"] else "")
        cell = f"`{r['cell']}`" + (f", tonemapped twin of `{r['twin_of']}`" if r["twin_of"] else "")
        lines.append(f"| {what} | {cell} | {r['queries']} | {r['recall@1_study']:.1f} | {r['recall@1_photo']:.1f} | "
                     f"{r['recall@1_photo'] - r['recall@1_study']:+.1f} | {r['recall@1_places_study']:.1f} | "
                     f"{r['recall@1_places_photo']:.1f} |")
    rescored = [r["method"] for r in rows if abs(r["recall@1_study_rescored"] - r["recall@1_study"]) > 0.005]
    lines += ["", "The same score of the database's rows (the study's frames, embedded by `monolib index`) gives the "
              "`cell.json` number " + ("for every method." if not rescored else
                                       "for every method but " + ", ".join(f"`{m}`" for m in rescored) +
                                       " (`recall@1_study_rescored` in the CSV)."), ""]
    lines += [
        "## Latency of one image", "",
        "Each image end to end, as `monolib localize` runs it: read (`Localizer.read`: the JPEG above decoded), "
        "then for a graph method segmentation, depth, graph (back-projection, nodes, edges) and encoder, for an "
        "image method its descriptor, then kNN (`Localizer.rank`: the nearest places over the database's rows). "
        "One torch thread; the first image untimed (a warm-up). Goal for a graph method: "
        f"{record['latency_goal_ms']:.0f} ms or less.", "",
        "| method | database rows | images | median ms | p90 ms | goal | median ms per stage |",
        "|---|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        stages = ", ".join(f"{s} {r[f'{s}_median_ms']:.1f}" for s in LATENCY_STAGES
                           if r.get(f"{s}_median_ms") is not None)
        if r["kind"] == "graph":
            over = r["latency_median_ms"] - record["latency_goal_ms"]
            goal = "met (median)" if over <= 0 else f"not met: median {over:.1f} ms over"
        else:
            goal = "(none)"
        lines.append(f"| `{r['method']}` | {r['database_frames']} | {r['latency_images']} | "
                     f"{r['latency_median_ms']:.1f} | {r['latency_p90_ms']:.1f} | {goal} | {stages} |")
    if "read_phone_photo_ms" in record:
        lines += ["", f"The photos above are {w} x {h}. A camera's JPEG costs more to read: a "
                  f"{PHONE_PHOTO[0]} x {PHONE_PHOTO[1]} JPEG (a frame enlarged, quality {record['jpeg_quality']}) "
                  f"takes {record['read_phone_photo_ms']:.1f} ms to decode (at a reduced DCT scale) and bring to "
                  f"{w} x {h}, against {record['read_study_photo_ms']:.1f} ms for a {w} x {h} one (median of 10)."]
    return "\n".join(lines) + "\n"
