"""`monolib bench localizers` (`make bench-localizers`, figures/localizers.json): what a localizer of each method
of a finished study costs, side by side: database bytes per frame, end-to-end milliseconds per query image
(perception, graph, embedding, search), and recall@1."""
from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np
import torch

from monolib import localize, methods
from monolib.bench.common import device_name, written
from monolib.data import selection
from monolib.data import dataset
from monolib.device import device
from monolib.params import load_study
from monolib.report.results import collect


def localizer_costs(study_name: str = "quick", queries: int = 40, out: str | None = None) -> dict:
    """What a localizer of each method of a finished study costs, side by side in one run: `monolib index` of the
    method's best cell into a temporary database, then `queries` test frames' RGB through `Localizer.stages` (the
    whole per-image pipeline of `monolib localize`: for a graph method segmentation, depth, graph and encoder; for
    an image method its descriptor) and a k-nearest search over the database. Per method: the database's bytes per
    frame (its embedding row) and in all (embeddings + the encoder's state), milliseconds per query by stage
    (first query a warm-up, not counted), and recall@1 of the ``paper`` protocol: the database cell's, and the mean
    over seeds of its scenario and threshold (`figures/results.csv` of the study's run)."""
    import os
    import tempfile


    study = load_study(study_name)
    torch.set_num_threads(study.threads)
    test = selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings).test
    step = max(1, len(test) // queries)
    frames = test[::step][:queries]
    results = collect(study.name)
    record = {"study": study.name, "machine": f"{platform.machine()} {platform.processor()}".strip(),
              "cpus": os.cpu_count(), "torch_threads": study.threads, "device": device_name(device()),
              "date": time.strftime("%Y-%m-%d"), "queries": len(frames), "methods": {}}
    names = study.graph_methods() + [m for m in study.methods if methods.kind(m, study) == "image"]
    print(f"localizer costs, study {study.name}, {len(frames)} query images of its test split, {study.threads} torch "
          f"thread(s), {record['device']} ({record['machine']}, {record['cpus']} cpus, {record['date']})")
    for method in names:
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            try:
                db = localize.build_index(study, Path(tmp) / "db", method)
            except localize.LocalizeError as e:  # HDR node colours: no database a photo can query
                if localize.HDR_REFUSED not in str(e):
                    raise
                record["methods"][method] = {"kind": "graph", "refused": "graphs.colour: hdr"}
                print(f"  {method:<17} graph refused: graphs.colour: hdr (a photo has no HDR radiance)")
                continue
            index_s = time.perf_counter() - t
            meta, table, emb = localize.read_database(db)
            loc = localize.Localizer.open(db)
            timings: dict = {}
            for f in frames[:1] + frames:  # the first: warm-up
                z = loc.stages(f.rgb, timings)
                t = time.perf_counter()
                torch.topk(torch.cdist(z[None], loc.embeddings), 10, largest=False)
                timings.setdefault("search", []).append(time.perf_counter() - t)
            state_bytes = (Path(db) / "encoder.pt").stat().st_size
        ms = {k: round(1000 * float(np.mean(v[1:])), 2) for k, v in timings.items()}
        same = results[(results.method == method) & (results.scenario == meta["scenario"])
                       & (results.threshold.astype(float) == float(meta["threshold"])) & (results.protocol == "paper")
                       & (results.metric == "recall") & (results.k == 1)]
        row = {"kind": meta.get("kind", "graph"), "scenario": meta["scenario"], "threshold": meta["threshold"],
               "dimensions": int(emb.shape[1]), "bytes_per_frame": int(emb[0].nbytes),
               "database_bytes": int(emb.nbytes), "encoder_state_bytes": int(state_bytes), "frames": int(len(emb)),
               "ms_per_query": ms, "ms_per_query_total": round(sum(ms.values()), 2), "index_s": round(index_s, 1),
               "recall@1_database_cell": round(float(meta["cell_recall@1"]), 2),
               "recall@1_mean_over_seeds": round(float(same["value"].mean()), 2) if len(same) else None,
               "seeds": int(same["seed"].nunique()) if len(same) else 0}
        record["methods"][method] = row
        print(f"  {method:<17} {row['kind']:<5} {meta['scenario']}@{meta['threshold']}: {row['dimensions']:>6}-d, "
              f"{row['bytes_per_frame']:>7,} B/frame, {row['ms_per_query_total']:8.1f} ms/query ("
              + ", ".join(f"{k} {v:.1f}" for k, v in ms.items()) + f"), recall@1 {row['recall@1_mean_over_seeds']} "
              f"(mean of {row['seeds']} seeds; the database's cell {row['recall@1_database_cell']})")
    return written(record, out, localizer_table)


def localizer_table(record: dict) -> str:
    """The table of `localizer_costs`' record (docs/benchmarks.md): one row per method."""
    lines = [f"**What a localizer costs** (`make bench-localizers`, study `{record['study']}`: "
             f"{record['queries']} query "
             f"images of its test split, {record['torch_threads']} torch thread(s), {record['device']}, "
             f"{record['machine']}, {record['cpus']} cpus, {record['date']}). Database: the method's embedding of each "
             f"of the study's test frames (float32), beside the encoder's state it needs (weights, a vocabulary). "
             f"Milliseconds per query image, end to end: perception (segmentation, depth), graph, embedding (the "
             f"encoder, or an image method's whole descriptor), search (k-nearest over the database). Recall@1: "
             f"`paper` protocol, the mean over seeds of the database cell's scenario and threshold.", "",
             "| method | data | dimensions | bytes / frame | encoder state | ms / query | of which | recall@1 |",
             "|---|---|---:|---:|---:|---:|---|---:|"]
    for method, r in record["methods"].items():
        if "refused" in r:
            lines.append(f"| `{method}` | refused: `{r['refused']}` (a photo has no HDR radiance) | | | | | | |")
            continue
        data = "RGB only" if r["kind"] == "image" else f"{r['scenario']} at {r['threshold']} m"
        parts = ", ".join(f"{k} {v:.1f}" for k, v in r["ms_per_query"].items())
        recall = "" if r["recall@1_mean_over_seeds"] is None else f"{r['recall@1_mean_over_seeds']:.1f}"
        lines.append(f"| `{method}` | {data} | {r['dimensions']:,} | {r['bytes_per_frame']:,} | "
                     f"{r['encoder_state_bytes'] / 1e6:.2f} MB | {r['ms_per_query_total']:.1f} | {parts} | {recall} |")
    return "\n".join(lines) + "\n"
