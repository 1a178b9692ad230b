"""Benchmarks that print figures (never asserted in tests): `monolib bench`.

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
- kNN over 600, 100k and 1M 64-d vectors: torch (cdist + topk) against a faiss flat index;
- `render_side_by_side` (`monolib bench --render-vs COMMIT`, `make bench-render`): the dataset stage of a study
  rendered by the generator of another commit and by this one, one after the other in one run;
- `localizer_costs` (`monolib bench --localizers`, `make bench-localizers`): what a localizer of each method of a
  finished study costs, side by side: database bytes per frame, end-to-end milliseconds per query image
  (perception, graph, embedding, search), and recall@1;
- `localize_photos` (`monolib bench --localize`, `make bench-localize`): recall@1 of the localizer of each method it
  offers when the frames of the study's test settings go through the photo path (JPEG, decoded, centre-cropped and
  resized), beside the same cells' recall@1 on the study's own frames; and one image's latency end to end on one
  torch thread, median and p90 (figures/localize.md and .csv);
- `imagenet_choices` (`monolib bench --imagenet-choices`, `make bench-imagenet`): `imagenet_vlad` as it is against
  PCA-whitened on the training split, recall@1 on both protocols (what decided `pretrained.VLAD_WHITEN`);
- `allocator_side_by_side` (`monolib bench --allocator`, `make bench-allocator`): one image cell of a finished study
  with glibc's malloc as it is and with `device.keep_freed_memory`, in a new process each: seconds, system CPU,
  page faults, and whether the two wrote the same files.
"""
from __future__ import annotations

import dataclasses
import platform
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from monolib import io, localize, methods, paths
from monolib.data import selection, stage as dataset, synth
from monolib.data.hypersim import Camera, HypersimDataset
from monolib.device import device
from monolib.graphs.build import at_threshold, build_scene_graph, complete_graph, scene_nodes
from monolib.io import write_json
from monolib.localize import Localizer
from monolib.params import PAPER, StudyError, load_study
from monolib.perception import depth as depth_net, features, segmentation, stage as perception
from monolib.report.results import cell_metrics, collect
from monolib.retrieval import evaluate, gcn, pretrained
from monolib.retrieval.metrics import metrics_from_hits


def _time(fn, repeat: int) -> float:
    fn()  # warm-up
    t = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat


def graph_ms(width: int, height: int, repeat: int = 10, seed: int = 0) -> float:
    """Milliseconds to back-project a frame and build its nodes + edges (30 labels, blocky layout)."""
    rgb, depth, semantic, cam = _bench_frame(width, height, seed)
    return 1000 * _time(lambda: at_threshold(complete_graph(*scene_nodes(rgb, depth, semantic, cam), "s", "f"), 2.0),
                        repeat)


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
    original_ms = 1000 * _time(lambda: original_graph(rgb, depth, semantic, cam, 2.0), repeat)
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
    torch_s = _time(lambda: torch.topk(torch.cdist(tq, tdb), k, largest=False), 3)
    index = faiss.IndexFlatL2(dim)
    index.add(db)
    faiss_s = _time(lambda: index.search(q, k), 3)
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
        s = _time(step, steps)
        per_epoch = int(np.ceil((ds.train_settings - spec.val_settings) * ds.train_frames_per_setting
                                / spec.batch_size))
        out[spec.name] = {"s_per_step": round(s, 3), "batch_size": spec.batch_size,
                          "resolution": f"{spec.train_width}x{spec.train_height}", "steps": per_epoch * spec.epochs,
                          "projected_hours": round(per_epoch * spec.epochs * s / 3600, 2)}
    out["projected_hours_all"] = round(sum(v["projected_hours"] for v in out.values()), 2)
    out["threads"] = torch.get_num_threads()
    return out


def device_name(dev: torch.device) -> str:
    """The GPU's name, or the CPU's model name (from /proc/cpuinfo where there is one)."""
    if dev.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(dev)}"
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
    except OSError:
        names = []
    return f"cpu: {names[0] if names else platform.processor() or platform.machine()}"


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
    with perception._threads(spec.threads), tempfile.TemporaryDirectory(prefix="monolib_fps_") as tmp:
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
                seconds = perception.predict_frames(model, task, shown, spec, lambda frame, prediction: None)
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


def render_side_by_side(old: str, study: str = "quick", out: str | None = None) -> dict:
    """The dataset stage of `study` (its whole mini-Hypersim, the study file's own workers) rendered by the code of
    commit `old` (a temporary git worktree) and by this checkout's, one after the other on this machine: wall
    seconds, frames and bytes of each. Run it on a quiet machine; with `out`, also written as JSON."""
    import os
    import shutil
    import subprocess
    import sys
    import tempfile

    repo = paths.PACKAGE.parent
    record = {"machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
              "date": time.strftime("%Y-%m-%d"), "study": study, "old_commit": old,
              "new_commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True,
                                    text=True).stdout.strip() + " + working tree"}
    with tempfile.TemporaryDirectory(prefix="monolib-render-") as tmp:
        tree = Path(tmp) / "old"
        subprocess.run(["git", "worktree", "add", "--detach", str(tree), old], cwd=repo, check=True,
                       capture_output=True)
        try:
            for label, root in (("old", tree), ("new", repo)):
                target = Path(tmp) / f"{label}-dataset"
                env = dict(os.environ, PYTHONPATH=str(root))
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-m", "monolib.cli", "synth", study, "--out", str(target)],
                               cwd=root, env=env, check=True)
                seconds = time.perf_counter() - t0
                frames = sum(1 for _ in target.glob("ai_*/images/*_final_hdf5/*.color.hdf5"))
                size = sum(f.stat().st_size for f in target.rglob("*") if f.is_file())
                record[label] = {"seconds": round(seconds, 1), "frames": frames, "gigabytes": round(size / 1e9, 2)}
                print(f"render {study} with the generator of {record[label + '_commit']}: "
                      f"{seconds:.1f} s, {frames} frames, {size / 1e9:.2f} GB", flush=True)
                shutil.rmtree(target)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=repo, capture_output=True)
    record["ratio"] = round(record["new"]["seconds"] / record["old"]["seconds"], 2)
    print(f"new / old: {record['ratio']:.2f}x the time ({record['machine']}, {record['cpus']} cpus, {record['date']})")
    if out:
        write_json(out, record)
    return record


ALLOCATOR_CELL = """
import json, resource, sys, time
from monolib.params import load_study
from monolib.retrieval import cell

study, method, seed, out = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
s = load_study(study)
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
cell.run_cell(s, method, "rgb", float("inf"), seed, out_dir=out, force=True)
wall, r1 = time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"seconds": wall, "user_s": r1.ru_utime - r0.ru_utime, "system_s": r1.ru_stime - r0.ru_stime,
                  "page_faults": r1.ru_minflt - r0.ru_minflt}))
"""


def allocator_side_by_side(study_name: str = "quick", method: str = "imagenet_triplet", seed: int = 0,
                           out: str | None = None) -> dict:
    """One image cell of a finished study (`method`, `seed`: its data and features cached) run twice in a new
    process each, one after the other: with malloc as glibc sets it (``MONOLIB_ALLOCATOR=default``) and with
    `device.keep_freed_memory` (``keep``). Per run: wall, user and system CPU seconds and minor page faults of the
    cell alone; and whether the two wrote the same files, bit for bit. With `out`, also JSON and its Markdown."""
    import hashlib
    import json
    import os
    import subprocess
    import sys
    import tempfile

    study = load_study(study_name)
    if methods.kind(method, study) != "image":
        raise StudyError(f"bench --allocator: {method!r} is not an image method of {study.path}")
    record = {"study": study.name, "method": method, "seed": seed, "torch_threads": study.threads,
              "machine": f"{platform.machine()} {platform.processor()}".strip(), "cpus": os.cpu_count(),
              "date": time.strftime("%Y-%m-%d"), "runs": {}}
    digests = {}
    with tempfile.TemporaryDirectory(prefix="monolib-allocator-") as tmp:
        for mode in ("default", "keep"):
            folder = Path(tmp) / mode
            done = subprocess.run([sys.executable, "-c", ALLOCATOR_CELL, str(study.path), method, str(seed),
                                   str(folder)], env={**os.environ, "MONOLIB_ALLOCATOR": mode}, check=True,
                                  capture_output=True, text=True)
            run = {k: round(v, 1) if k != "page_faults" else int(v)
                   for k, v in json.loads(done.stdout.strip().splitlines()[-1]).items()}
            run["system_share"] = round(run["system_s"] / max(run["user_s"] + run["system_s"], 1e-9), 3)
            run["page_faults_per_s"] = int(run["page_faults"] / max(run["seconds"], 1e-9))
            record["runs"][mode] = run
            digests[mode] = {f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in sorted(folder.iterdir())
                             if f.suffix in (".npy", ".csv", ".pt")}
            print(f"{method} seed {seed} of {study.name}, MONOLIB_ALLOCATOR={mode}: {run['seconds']:.1f} s "
                  f"(user {run['user_s']:.1f} s, system {run['system_s']:.1f} s), {run['page_faults']:,} page faults",
                  flush=True)
    record["same_files"] = digests["default"] == digests["keep"]
    record["files_compared"] = sorted(digests["keep"])
    record["speedup"] = round(record["runs"]["default"]["seconds"] / record["runs"]["keep"]["seconds"], 2)
    print(f"default / keep: {record['speedup']:.2f}x the time; the same files: {record['same_files']} "
          f"({', '.join(record['files_compared'])})")
    return _written(record, out, allocator_table)


def allocator_table(record: dict) -> str:
    """The table of `allocator_side_by_side`'s record (docs/benchmarks.md)."""
    lines = [f"**The allocator** (`make bench-allocator`: one `{record['method']}` cell of `{record['study']}`, seed "
             f"{record['seed']}, in a new process each, {record['torch_threads']} torch thread(s), "
             f"{record['machine']}, {record['cpus']} cpus, {record['date']}). The same files, bit for bit "
             f"({', '.join(record['files_compared'])}): **{'yes' if record['same_files'] else 'NO'}**.", "",
             "| MONOLIB_ALLOCATOR | seconds | user CPU s | system CPU s | system share | page faults | faults / s |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for mode, r in record["runs"].items():
        lines.append(f"| `{mode}` | {r['seconds']:.1f} | {r['user_s']:.1f} | {r['system_s']:.1f} | "
                     f"{100 * r['system_share']:.0f}% | {r['page_faults']:,} | {r['page_faults_per_s']:,} |")
    return "\n".join(lines) + "\n"


def _written(record: dict, out: str | None, table) -> dict:
    """`record`, written to `out` (JSON) and beside it as the Markdown `table(record)` (docs/benchmarks.md)."""
    if out:
        write_json(out, record)
        io.write_text(Path(out).with_suffix(".md"), table(record))
        print(f"written: {out} and {Path(out).with_suffix('.md')}")
    return record


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
    return _written(record, out, localizer_table)


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


def imagenet_choices(study_name: str = "quick", seeds=(0, 1), dims=(None, 128, 256, 512),
                     out: str | None = None) -> dict:
    """The measurement behind `pretrained.VLAD_WHITEN`: `imagenet_vlad` without and with PCA whitening learnt on the
    training split, per seed, recall@1 of both protocols on the study's test split (`evaluate.evaluate_protocols`,
    the cells' evaluation). (How `imagenet_triplet` trains is chosen on the training split alone:
    `monolib.retrieval.model_selection`.)"""
    study = load_study(study_name)
    torch.set_num_threads(study.threads)
    sel = selection.select_frames(study, dataset.open_dataset(study), study.gcn.val_settings)
    train = np.concatenate([features.load(study, sel.train), features.load(study, sel.val)])
    test = features.load(study, sel.test)
    _, head = features.networks()
    keys, settings = [f.key for f in sel.test], [f.setting for f in sel.test]
    record = {"study": study.name, "machine": f"{platform.machine()} {platform.processor()}".strip(),
              "date": time.strftime("%Y-%m-%d"), "vlad_whitening": []}
    for seed in seeds:
        for d in dims:
            t = time.perf_counter()
            emb, _, _ = pretrained.vlad_embed(train, test, head, seed, whiten_dims=d)
            r = evaluate.evaluate_protocols(emb, keys, settings, study.protocol, seed)
            row = {"seed": seed, "whitened_dims": d, "dimensions": int(emb.shape[1]),
                   **{f"recall@1_{p}": round(float(v.metrics["recall@1"]), 1) for p, v in r.items()},
                   "seconds": round(time.perf_counter() - t, 1)}
            record["vlad_whitening"].append(row)
            print(f"imagenet_vlad seed {seed}, whitened to {d or 'none (as it is)'}: {row['dimensions']}-d, "
                  + ", ".join(f"{k} {v}" for k, v in row.items() if k.startswith("recall")), flush=True)
    return _written(record, out, imagenet_choices_table)


def imagenet_choices_table(record: dict) -> str:
    protos = [k for k in record["vlad_whitening"][0] if k.startswith("recall@1_")] if record["vlad_whitening"] else []
    head = " | ".join(p.replace("recall@1_", "recall@1 ") for p in protos)
    lines = [f"**Whitening of `imagenet_vlad`** (`monolib bench --imagenet-choices`, study `{record['study']}`, "
             f"{record['machine']}, {record['date']}; recall@1 on the test split, both protocols).", "",
             f"| imagenet_vlad | seed | dimensions | {head} |", "|---|---:|---:|" + "---:|" * len(protos)]
    for r in record["vlad_whitening"]:
        what = f"PCA-whitened to {r['whitened_dims']}" if r["whitened_dims"] else "as it is (chosen)"
        lines.append(f"| {what} | {r['seed']} | {r['dimensions']:,} | "
                     + " | ".join(f"{r[p]:.1f}" for p in protos) + " |")
    return "\n".join(lines) + "\n"

# ---- localizing photos: recall@1 through the photo path, and one image's latency ---------------------------

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


def _cpu() -> str:
    return device_name(torch.device("cpu")).removeprefix("cpu: ")


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
    import cv2
    import os
    import tempfile

    start = time.perf_counter()
    study = load_study(study_name)
    old_threads, old_cv = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    record = {"study": study.name, "cpu": _cpu(), "cores": os.cpu_count(), "torch_threads": 1,
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
        f"`monolib bench --localize --study {record['study']}` (`make bench-localize` for `quick`), "
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
