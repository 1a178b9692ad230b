"""Benchmarks that print figures (never asserted in tests): `monolib bench`.

- rendering: frames per second of the mini-Hypersim renderer;
- per-frame stages of the localizer at the study's resolution: segmentation, depth, back-projection + graph,
  encoder, and kNN over the 656 test frames; the networks are built from the study's specs (trained weights
  change nothing about speed);
- graph construction alone at 256x192 and 1024x768;
- kNN over 600, 100k and 1M 64-d vectors: torch (cdist + topk) against a faiss flat index.
"""
from __future__ import annotations

import platform
import time

import numpy as np
import pandas as pd
import torch

from monolib.graph import scene_nodes
from monolib.hypersim import Camera


def _time(fn, repeat: int) -> float:
    fn()  # warm-up
    t = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat


def graph_ms(width: int, height: int, repeat: int = 10, seed: int = 0) -> float:
    """Milliseconds to back-project a frame and build its nodes + edges (30 labels, blocky layout)."""
    from monolib.graph import at_threshold, complete_graph

    rng = np.random.default_rng(seed)
    blocks = rng.integers(1, 31, (12, 16))
    semantic = np.kron(blocks, np.ones((height // 12 + 1, width // 16 + 1), np.int64))[:height, :width].astype(np.int16)
    depth = rng.uniform(0.5, 8.0, (height, width)).astype(np.float32)
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    cam = Camera.canonical(width, height)
    return 1000 * _time(lambda: at_threshold(complete_graph(*scene_nodes(rgb, depth, semantic, cam), "s", "f"), 2.0), repeat)


def knn_ms(n: int, dim: int = 64, queries: int = 100, k: int = 10, seed: int = 0) -> dict:
    import faiss

    rng = np.random.default_rng(seed)
    db = rng.normal(size=(n, dim)).astype(np.float32)
    q = rng.normal(size=(queries, dim)).astype(np.float32)
    tdb, tq = torch.from_numpy(db), torch.from_numpy(q)
    torch_s = _time(lambda: torch.topk(torch.cdist(tq, tdb), k, largest=False), 3)
    index = faiss.IndexFlatL2(dim)
    index.add(db)
    faiss_s = _time(lambda: index.search(q, k), 3)
    return {"database": n, "queries": queries, "torch_ms_per_query": 1000 * torch_s / queries,
            "faiss_ms_per_query": 1000 * faiss_s / queries}


def stage_ms(study_name: str = "quick", frames: int = 20) -> dict:
    """Per-frame milliseconds of each localizer stage at the study's resolution (untrained weights)."""
    from monolib import depth, gcn, segmentation
    from monolib.localize import Localizer
    from monolib.params import load_study

    study = load_study(study_name, check_files=False)
    torch.set_num_threads(study.threads)
    w, h = study.dataset.width, study.dataset.height
    sc = [s for s in study.scenarios.values() if s.depth != "gt" and s.semantic != "gt"]
    seg = segmentation.build_model(study.perception.segmentation)
    dep = depth.build_model(study.depth_spec(sc[0].depth) if sc else study.perception.depth[0])
    n_db = study.protocol.settings * study.protocol.frames
    loc = Localizer(study, {"width": w, "height": h, "threshold": 2.0}, seg.eval(), dep.eval(),
                    gcn.GraphEncoder(study.gcn).eval(), torch.randn(n_db, study.gcn.out),
                    pd.DataFrame({"frame": [str(i) for i in range(n_db)], "setting": [str(i % 16) for i in range(n_db)]}))
    rng = np.random.default_rng(0)
    timings: dict = {}
    for _ in range(frames + 1):
        rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        z = loc.stages(rgb, timings)
        t = time.perf_counter()
        torch.topk(torch.cdist(z[None], loc.embeddings), 10, largest=False)
        timings.setdefault("knn", []).append(time.perf_counter() - t)
    out = {k: 1000 * float(np.mean(v[1:])) for k, v in timings.items()}  # first frame = warm-up
    out["total"] = sum(out.values())
    out["graph_share_%"] = 100 * out["graph"] / out["total"]
    return out


def run(width: int = 256, height: int = 192, study: str = "quick", out: str | None = None) -> dict:
    """Print every benchmark; with `out`, also write them as JSON (the README quotes `figures/bench.json`)."""
    import os

    print(f"machine: {platform.machine()} {platform.processor()}, {os.cpu_count()} cpus, "
          f"{torch.get_num_threads()} torch threads, torch {torch.__version__}")
    from monolib import synth

    record = {"machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
              "torch_threads": torch.get_num_threads(), "date": time.strftime("%Y-%m-%d")}
    r = synth.benchmark(width, height, frames=10)
    record["render_frames_per_s"] = round(r["fps"], 2)
    st = stage_ms(study)
    record["stage_ms_per_frame"] = {k: round(v, 2) for k, v in st.items()}
    print(f"per-frame stages at the {study} study's resolution (ms): "
          + ", ".join(f"{k} {v:.1f}" for k, v in st.items() if k != "graph_share_%")
          + f"; graph = {st['graph_share_%']:.1f}% of the frame")
    record["graph_ms_per_frame"] = {}
    for w, h in ((256, 192), (1024, 768)):
        ms = graph_ms(w, h)
        record["graph_ms_per_frame"][f"{w}x{h}"] = round(ms, 2)
        print(f"graph construction {w}x{h}: {ms:.1f} ms per frame")
    record["knn_ms_per_query"] = {}
    for n in (600, 100_000, 1_000_000):
        r = knn_ms(n)
        record["knn_ms_per_query"][f"{n}"] = {"torch": round(r["torch_ms_per_query"], 4),
                                              "faiss_flat": round(r["faiss_ms_per_query"], 4)}
        print(f"kNN over {n:>9,} vectors (64-d, k=10): torch {r['torch_ms_per_query']:.3f} ms/query, "
              f"faiss flat {r['faiss_ms_per_query']:.3f} ms/query")
    if out:
        from monolib.io import write_json

        write_json(out, record)
        print(f"written: {out}")
    return record
