"""`monolib bench frames` (`make bench`, figures/bench.json): what one frame costs.

- rendering: frames per second of the mini-Hypersim renderer;
- per-frame stages of the localizer at the study's resolution: segmentation, depth, back-projection + graph,
  encoder, and kNN over the 656 test frames; the networks are built from the study's specs (trained weights
  change nothing about speed);
- graph construction alone at 256x192 and 1024x768, and against the original code's way (a Python double loop over
  the pixels, `original_graph`) on the same frames in the same run: the speedup ratio;
- `make zoo`'s training time on this machine, projected from timed training steps of params/zoo.yaml's networks;
- perception frames per second at 256x192 and 1024x768: each network of the study's perception block predicting
  frames written in the Hypersim layout, through the perception stage's own DataLoader + batched predict path
  (`perception.predict_frames`; untrained weights, the model's input at the measured resolution);
- kNN over 600, 100k and 1M 64-d vectors: torch (cdist + topk) against a faiss flat index.
"""
from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from monolib import io
from monolib.bench.common import device_name, seconds_per_call
from monolib.data import synth
from monolib.data.hypersim import Camera, HypersimDataset
from monolib.device import device
from monolib.graphs.build import at_threshold, build_scene_graph, complete_graph, scene_nodes
from monolib.io import write_json
from monolib.localize import Localizer
from monolib.params import load_study
from monolib.perception import depth as depth_net
from monolib.perception import segmentation
from monolib.perception import predictions
from monolib.retrieval import gcn


def graph_ms(width: int, height: int, repeat: int = 10, seed: int = 0) -> float:
    """Milliseconds to back-project a frame and build its nodes + edges (30 labels, blocky layout)."""
    rgb, depth, semantic, cam = _bench_frame(width, height, seed)
    return 1000 * seconds_per_call(
        lambda: at_threshold(complete_graph(*scene_nodes(rgb, depth, semantic, cam), "s", "f"), 2.0), repeat)


def original_graph(rgb: np.ndarray, depth: np.ndarray, semantic: np.ndarray, camera: Camera, threshold: float):
    """The graph of a frame built the way the original published code builds it: a Python double loop over the
    pixels gathers each label's 3D points and colours, then per-label medians (numpy), then a double loop over
    node pairs for the edges. The reference the benchmark compares ours with (same nodes, same edges).
    Returns (x (L, 4), pos (L, 3), edges [(i, j, length)], both directions)."""
    height, width = depth.shape
    rays = camera.rays(height, width)
    points: dict[int, list] = {}
    colours: dict[int, list] = {}
    for v in range(height):
        for u in range(width):
            label, d = int(semantic[v, u]), float(depth[v, u])
            if label < 1 or not d > 0:
                continue
            ray = rays[v, u]
            points.setdefault(label, []).append(ray * (d / -ray[2]))
            colours.setdefault(label, []).append(rgb[v, u])
    labels = sorted(points)
    pos = np.array([np.median(np.array(points[k]), axis=0) for k in labels]).reshape(-1, 3)
    col = np.array([np.median(np.array(colours[k], dtype=np.float64), axis=0) / 255.0 for k in labels]).reshape(-1, 3)
    x = np.concatenate([np.array(labels, np.float64)[:, None], col], axis=1)
    edges = []
    for i in range(len(labels)):
        for j in range(i + 1, len(labels)):
            length = float(np.linalg.norm(pos[i] - pos[j]))
            if length < threshold:
                edges += [(i, j, length), (j, i, length)]
    return x, pos, edges


def _bench_frame(width: int, height: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    blocks = rng.integers(1, 31, (12, 16))
    semantic = np.kron(blocks, np.ones((height // 12 + 1, width // 16 + 1), np.int64))[:height, :width].astype(np.int16)
    depth = rng.uniform(0.5, 8.0, (height, width)).astype(np.float32)
    rgb = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    return rgb, depth, semantic, Camera.canonical(width, height)


def graph_speedup(width: int, height: int, ours_ms: float, repeat: int = 1) -> dict:
    """Ours (`ours_ms`, from `graph_ms` on the same frame in the same run) against `original_graph`: milliseconds
    of each, the ratio, and whether the two give the same nodes and edge count."""
    rgb, depth, semantic, cam = _bench_frame(width, height)
    original_ms = 1000 * seconds_per_call(lambda: original_graph(rgb, depth, semantic, cam, 2.0), repeat)
    g = build_scene_graph(rgb, depth, semantic, cam, 2.0)
    x, pos, edges = original_graph(rgb, depth, semantic, cam, 2.0)
    same = bool(np.allclose(g.x.numpy(), x, atol=1e-5) and np.allclose(g.pos.numpy(), pos, atol=1e-4)
                and g.edge_index.shape[1] == len(edges))
    return {"ours_ms": round(ours_ms, 2), "original_ms": round(original_ms, 1),
            "speedup": round(original_ms / ours_ms, 1), "same_graph": same}


def knn_ms(n: int, dim: int = 64, queries: int = 100, k: int = 10, seed: int = 0) -> dict:
    import faiss

    rng = np.random.default_rng(seed)
    db = rng.normal(size=(n, dim)).astype(np.float32)
    q = rng.normal(size=(queries, dim)).astype(np.float32)
    tdb, tq = torch.from_numpy(db), torch.from_numpy(q)
    torch_s = seconds_per_call(lambda: torch.topk(torch.cdist(tq, tdb), k, largest=False), 3)
    index = faiss.IndexFlatL2(dim)
    index.add(db)
    faiss_s = seconds_per_call(lambda: index.search(q, k), 3)
    return {"database": n, "queries": queries, "torch_ms_per_query": 1000 * torch_s / queries,
            "faiss_ms_per_query": 1000 * faiss_s / queries}


def stage_ms(study_name: str = "quick", frames: int = 20) -> dict:
    """Per-frame milliseconds of each localizer stage at the study's resolution (untrained weights)."""
    study = load_study(study_name, check_files=False)
    torch.set_num_threads(study.threads)
    w, h = study.dataset.width, study.dataset.height
    sc = [s for s in study.scenarios.values() if s.depth != "gt" and s.semantic != "gt"]
    seg = segmentation.build_model(study.perception.segmentation)
    dep = depth_net.build_model(study.depth_spec(sc[0].depth) if sc else study.perception.depth[0])
    n_db = study.protocol.settings * study.protocol.frames
    loc = Localizer(study, {"width": w, "height": h, "threshold": 2.0}, seg.eval(), dep.eval(),
                    gcn.GraphEncoder(study.gcn).eval(), torch.randn(n_db, study.gcn.out),
                    pd.DataFrame({"frame": [str(i) for i in range(n_db)],
                                  "setting": [str(i % 16) for i in range(n_db)]}))
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


def zoo_training(study_name: str = "zoo", steps: int = 3) -> dict:
    """Seconds per training step (forward, backward, AdamW; random images at the spec's batch size and resolution)
    of each network of the zoo study, and `make zoo`'s training time on this machine projected from it: steps per
    epoch x epochs (validation and rendering not counted)."""
    study = load_study(study_name, check_files=False)
    ds = study.dataset
    out = {}
    specs = [(study.perception.segmentation, "segmentation")] + [(d, "depth") for d in study.perception.depth]
    for spec, task in specs:
        model = segmentation.build_model(spec) if task == "segmentation" else depth_net.build_model(spec)
        opt = torch.optim.AdamW(model.parameters(), lr=spec.lr)
        x = torch.randn(spec.batch_size, 3, spec.train_height, spec.train_width)
        if task == "segmentation":
            y = torch.randint(0, 40, (spec.batch_size, spec.train_height, spec.train_width))
            loss_of = lambda: torch.nn.functional.cross_entropy(model(x)["out"], y)  # noqa: E731
        else:
            y = torch.rand(spec.batch_size, spec.train_height, spec.train_width) * 5 + 0.5
            loss_of = lambda: depth_net.depth_loss(model(x)[:, 0], y)  # noqa: E731

        def step():
            loss = loss_of()
            opt.zero_grad()
            loss.backward()
            opt.step()

        model.train()
        s = seconds_per_call(step, steps)
        per_epoch = int(np.ceil((ds.train_settings - spec.val_settings) * ds.train_frames_per_setting
                                / spec.batch_size))
        out[spec.name] = {"s_per_step": round(s, 3), "batch_size": spec.batch_size,
                          "resolution": f"{spec.train_width}x{spec.train_height}", "steps": per_epoch * spec.epochs,
                          "projected_hours": round(per_epoch * spec.epochs * s / 3600, 2)}
    out["projected_hours_all"] = round(sum(v["projected_hours"] for v in out.values()), 2)
    out["threads"] = torch.get_num_threads()
    return out


def write_frames(root, width: int, height: int, frames: int, seed: int = 0):
    """`frames` random HDR colour frames of one setting in the Hypersim layout under `root` (the colour files only,
    gzip as Hypersim's); returns them as `Frame`s of a `HypersimDataset`."""
    rng = np.random.default_rng(seed)
    images = Path(root) / "ai_000_001" / "images" / "scene_cam_00_final_hdf5"
    for i in range(frames):
        io.write_h5(images / f"frame.{i:04d}.color.hdf5",
                    rng.random((height, width, 3), np.float32).astype(np.float16), 1)
    return HypersimDataset(root).frames("ai_000_001")


def perception_fps(study_name: str = "quick", sizes=((256, 192), (1024, 768)), frames=(16, 4)) -> dict:
    """Frames per second of each network of the study's perception block (segmentation, then each depth net) at
    each size (width, height): `frames[k]` frames at `sizes[k]`, written in the Hypersim layout to a temporary
    folder and predicted with `perception.predict_frames` (the stage's DataLoader of `loader_workers` processes,
    batches of `predict_batch`, `amp` on CUDA) at the study's torch threads; the network is built from the study's
    spec with its input at that size (untrained weights: speed does not depend on them). `fps`: frames over the
    wall-clock time of the whole pass (reading included); `inference_fps`: over the forward passes alone. One
    frame is predicted first as a warm-up, untimed."""
    import dataclasses
    import tempfile

    study = load_study(study_name, check_files=False)
    spec = study.perception
    dev = device()
    nets = [(spec.segmentation, "segmentation")] + [(d, "depth") for d in spec.depth]
    out = {"study": study_name, "device": device_name(dev), "batch": spec.predict_batch,
           "loader_workers": spec.loader_workers, "amp": spec.amp and dev.type == "cuda", "threads": spec.threads,
           "networks": {}}
    with predictions._threads(spec.threads), tempfile.TemporaryDirectory(prefix="monolib_fps_") as tmp:
        for (width, height), n in zip(sizes, frames):
            size = f"{width}x{height}"
            shown = write_frames(Path(tmp) / size, width, height, n)
            for net_spec, task in nets:
                s = dataclasses.replace(net_spec, pretrained=False, train_width=width, train_height=height)
                if task == "segmentation":
                    model = segmentation.build_model(s)
                elif s.checkpoint:  # an AdelaiDepth checkpoint: LeReS's own widths
                    model = depth_net.build_leres(s.backbone, (height, width))
                else:
                    model = depth_net.build_model(s)
                model = model.to(dev).eval()
                predict = segmentation.predict if task == "segmentation" else depth_net.predict
                predict(model, shown[0].rgb, spec.predict_batch, amp=spec.amp)  # warm-up, one frame
                t = time.perf_counter()
                seconds = predictions.predict_frames(model, task, shown, spec, lambda frame, prediction: None)
                wall = time.perf_counter() - t
                out["networks"].setdefault(net_spec.name, {"task": task, "backbone": net_spec.backbone})[size] = {
                    "frames": n, "fps": round(n / wall, 2), "inference_fps": round(n / seconds, 2)}
    return out


def run(width: int = 256, height: int = 192, study: str = "quick", out: str | None = None) -> dict:
    """Print every benchmark; with `out`, also write them as JSON (docs/benchmarks.md shows `figures/bench.json`)."""
    import os

    print(f"machine: {platform.machine()} {platform.processor()}, {os.cpu_count()} cpus, "
          f"{torch.get_num_threads()} torch threads, torch {torch.__version__}")

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
    z = zoo_training()
    record["zoo_training"] = z
    print("make zoo's training on this machine (params/zoo.yaml, projected from timed steps): " + ", ".join(
        f"{k} {v['s_per_step']:.2f} s/step x {v['steps']} steps = {v['projected_hours']:.1f} h" for k, v in z.items()
        if isinstance(v, dict)) + f"; all {z['projected_hours_all']:.1f} h")
    record["graph_vs_original"] = {}
    for w, h in ((256, 192), (1024, 768)):
        r = graph_speedup(w, h, record["graph_ms_per_frame"][f"{w}x{h}"])
        record["graph_vs_original"][f"{w}x{h}"] = r
        print(f"graph construction {w}x{h}, ours against the original's pixel double loop (same frame, this run): "
              f"{r['ours_ms']:.1f} ms vs {r['original_ms']:.0f} ms, {r['speedup']:.0f}x faster, "
              f"same graph: {r['same_graph']}")
    p = perception_fps(study)
    record["perception_fps"] = p
    first = next(iter(p["networks"].values()))
    heads = {size: f"{size} ({r['frames']} frames)" for size, r in first.items() if "x" in size}
    print(f"perception frames per second, the {study} study's networks (untrained) through the stage's DataLoader + "
          f"predict, reading included (in brackets: the forward passes alone); {p['device']}, batch {p['batch']}, "
          f"{p['loader_workers']} loader workers, amp {'on' if p['amp'] else 'off'}, {p['threads']} torch threads:")
    print(f"  {'network':<12} {'backbone':<20}" + "".join(f"{h:>24}" for h in heads.values()))
    for name, r in p["networks"].items():
        cells = [f"{r[size]['fps']:.2f} ({r[size]['inference_fps']:.2f})" for size in heads]
        print(f"  {name:<12} {r['backbone']:<20}" + "".join(f"{c:>24}" for c in cells))
    record["knn_ms_per_query"] = {}
    for n in (600, 100_000, 1_000_000):
        r = knn_ms(n)
        record["knn_ms_per_query"][f"{n}"] = {"torch": round(r["torch_ms_per_query"], 4),
                                              "faiss_flat": round(r["faiss_ms_per_query"], 4)}
        print(f"kNN over {n:>9,} vectors (64-d, k=10): torch {r['torch_ms_per_query']:.3f} ms/query, "
              f"faiss flat {r['faiss_ms_per_query']:.3f} ms/query")
    if out:
        write_json(out, record)
        print(f"written: {out}")
    return record
