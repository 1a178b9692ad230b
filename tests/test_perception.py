"""Perception: DeepLabV3 and the LeReS-style depth net learn, the prediction cache round-trips, degenerate frames
(all-NaN depth, no labelled pixel) pass through evaluation and the graph-stage readers, and a re-run does no work.

Every test uses a tiny hand-made dataset in the Hypersim layout (`make_tiny_dataset`) under a temporary `runs/`,
so that the file runs beside the tests that share the checkout's `runs/` (the smoke study's perception rerun is in
test_study.py).
"""
from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest
import torch

from monolib import io, paths
from monolib.params import load_study

pytestmark = pytest.mark.filterwarnings("ignore:.*canonical 60-degree camera")

H, W = 48, 64
CLASSES = {1: (150, 140, 130), 2: (90, 60, 40), 5: (200, 40, 40), 7: (40, 160, 60), 11: (40, 60, 200)}


def make_tiny_dataset(root: Path, train: int = 4, test: int = 2, frames: int = 6, seed: int = 0) -> None:
    """A Hypersim-layout folder: wall (1) over floor (2) with a few coloured boxes (5, 7, 11), depth from a room.

    The first test frame has NaN depth everywhere and the second one no labelled pixel.
    """
    rng = np.random.default_rng(seed)
    rows = []
    names = ([(f"ai_001_{i + 1:03d}", "train") for i in range(train)]
             + [(f"ai_{i + 2:03d}_001", "test") for i in range(test)])
    for s, (setting, part) in enumerate(names):
        for k in range(frames):
            sem = np.ones((H, W), np.int16)
            horizon = int(rng.integers(H // 3, 2 * H // 3))
            sem[horizon:] = 2
            wall = 2.0 + 2.0 * rng.random()
            yy = np.arange(H)[:, None].repeat(W, 1).astype(np.float32)
            depth = np.full((H, W), wall, np.float32)
            floor = (yy - horizon + 1.0) / (H - horizon + 1.0)
            depth[horizon:] = (wall / (1.0 + 2.0 * floor))[horizon:]
            for cls in (5, 7, 11):
                h0, w0 = int(rng.integers(6, 16)), int(rng.integers(8, 20))
                r0, c0 = int(rng.integers(0, H - h0)), int(rng.integers(0, W - w0))
                sem[r0 : r0 + h0, c0 : c0 + w0] = cls
                depth[r0 : r0 + h0, c0 : c0 + w0] = np.minimum(depth[r0 : r0 + h0, c0 : c0 + w0], 0.6 * wall)
            col = np.zeros((H, W, 3), np.float32)
            for cls, rgb in CLASSES.items():
                col[sem == cls] = np.array(rgb, np.float32) / 255.0
            col = col * (0.5 + 0.5 * rng.random()) + rng.normal(0, 0.02, col.shape).astype(np.float32)
            col = np.clip(col, 0, 1) ** 2.2
            if part == "test" and s == train and k == 0:
                depth[:] = np.nan
            if part == "test" and s == train and k == 1:
                sem[:] = -1
            base = root / setting / "images"
            io.write_h5(base / "scene_cam_00_final_hdf5" / f"frame.{k:04d}.color.hdf5", col.astype(np.float16), 1)
            geo = base / "scene_cam_00_geometry_hdf5"
            io.write_h5(geo / f"frame.{k:04d}.depth_meters.hdf5", depth.astype(np.float16), 1)
            io.write_h5(geo / f"frame.{k:04d}.semantic.hdf5", sem, 1)
            io.write_h5(geo / f"frame.{k:04d}.render_entity_id.hdf5", np.where(sem == -1, 0, 1).astype(np.int32), 1)
            rows.append([setting, "cam_00", k, "True", "", part])
    with open(root / "metadata_images_split_scene_v1.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene_name", "camera_name", "frame_id", "included_in_public_release", "exclude_reason",
                    "split_partition_name"])
        w.writerows(rows)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_hypersim")
    make_tiny_dataset(root)
    return root


@pytest.fixture
def tiny_study(tiny, tmp_path, monkeypatch):
    """The smoke study pointed at the tiny dataset, tiny networks, runs/ and figures/ in a temporary folder."""
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    s = load_study("smoke")
    s.dataset.source, s.dataset.root = "hypersim", str(tiny)
    s.dataset.width, s.dataset.height, s.dataset.train_frames_per_setting = W, H, 6
    s.protocol.settings, s.protocol.frames, s.protocol.queries, s.protocol.positives = 2, 6, 4, 2
    s.protocol.siblings = 0  # test settings of two families, no siblings
    s.perception.threads = 1
    seg = s.perception.segmentation
    seg.epochs, seg.batch_size, seg.train_height, seg.train_width, seg.val_settings = 2, 6, H, W, 1
    for d in s.perception.depth:
        d.epochs, d.batch_size, d.train_height, d.train_width, d.val_settings, d.decoder_width = 2, 6, H, W, 1, 16
    return s


def _frames(study, val=1):
    from monolib.data.selection import select_frames
    from monolib.data.dataset import open_dataset

    return select_frames(study, open_dataset(study), val)


def _falls(losses):
    k = max(2, len(losses) // 4)
    return float(np.mean(losses[-k:])) < float(np.mean(losses[:k]))


@pytest.mark.slow
def test_segmentation_loss_falls(tiny_study):
    from monolib.perception import segmentation

    torch.set_num_threads(1)
    spec = tiny_study.perception.segmentation
    spec.epochs, spec.lr = 12, 3e-3
    sel = _frames(tiny_study)
    losses = []
    model, hist = segmentation.train(spec, sel.train, [], seed=0, progress=False,
                                     step_callback=lambda step, loss: losses.append(loss))
    assert len(losses) >= 10 and _falls(losses), losses
    pred = segmentation.predict(model, np.stack([f.rgb for f in sel.test[:2]]))
    assert pred.dtype == np.int16 and pred.shape == (2, H, W) and pred.min() >= 1 and pred.max() <= 40


@pytest.mark.slow
def test_depth_loss_falls(tiny_study):
    from monolib.perception import depth

    torch.set_num_threads(1)
    spec = tiny_study.perception.depth[0]
    spec.epochs, spec.lr = 12, 3e-3
    sel = _frames(tiny_study)
    losses = []
    model, hist = depth.train(spec, sel.train, [], seed=0, progress=False,
                              step_callback=lambda step, loss: losses.append(loss))
    assert len(losses) >= 10 and _falls(losses), losses
    pred = depth.predict(model, np.stack([f.rgb for f in sel.test[:2]]))
    assert pred.dtype == np.float32 and pred.shape == (2, H, W) and np.isfinite(pred).all() and (pred > 0).all()


def test_normalise_stays_on_the_device_of_its_input():
    """The ImageNet constants are built on the CPU at import; images on another device (a GPU, here the `meta`
    device, which fails on any mix of devices) must not meet them there (the crash seen on a GPU)."""
    from monolib.perception import segmentation

    x = torch.zeros((2, 3, 8, 8), dtype=torch.uint8, device="meta")
    out = segmentation.normalise(x)
    assert out.device.type == "meta" and out.shape == (2, 3, 8, 8) and out.dtype == torch.float32


def test_depth_loss_masks_nan():
    from monolib.perception.depth import depth_loss

    pred = torch.zeros(2, 8, 8, requires_grad=True)
    gt = torch.full((2, 8, 8), float("nan"))
    gt[1, :4] = 2.0
    loss = depth_loss(pred, gt)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()
    assert float(depth_loss(pred, torch.full((2, 8, 8), float("nan")))) == 0.0


def test_metrics_on_degenerate_frames():
    from monolib.perception.predictions import evaluate_depth, evaluate_segmentation

    gt = np.array([[1, 2], [2, -1]], np.int16)
    empty = np.full((2, 2), -1, np.int16)
    s = evaluate_segmentation([(gt, gt), (empty, gt), (None, gt)])
    assert s["pixel_accuracy"] == 1.0 and s["miou"] == 1.0 and s["pixels"] == 3
    nan = np.full((2, 2), np.nan, np.float32)
    d = np.array([[1.0, 2.0], [np.nan, 4.0]], np.float32)
    m = evaluate_depth([(nan, d), (d, d * 1.1)])
    assert m["frames"] == 1 and np.isclose(m["abs_rel"], 0.1, atol=1e-5) and m["delta1"] == 1.0
    assert np.isclose(m["median_ratio"], 1.1, atol=1e-5)
    assert np.isnan(evaluate_depth([(nan, d)])["abs_rel"])


@pytest.mark.slow
def test_run_caches_and_round_trips(tiny_study):
    from monolib.perception import depth, predictions, segmentation

    table = predictions.run(tiny_study, progress=False)
    assert set(table.attrs["status"].values()) == {"done"}
    assert np.isfinite(table["value"]).all(), table
    assert (paths.figures_dir("smoke") / "perception.csv").is_file()
    sel = _frames(tiny_study)
    frames = sel.all()
    seg_name = tiny_study.perception.segmentation.name
    d_name = tiny_study.perception.depth[0].name
    # every frame is cached; the cache equals what the saved model predicts (write -> read equals)
    model = segmentation.load_model(tiny_study.perception.segmentation,
                                    predictions.model_dir(tiny_study, seg_name) / "model.pt")
    fresh = segmentation.predict(model, np.stack([f.rgb for f in frames[:4]]), amp=tiny_study.perception.amp)
    read = predictions.semantic_source(tiny_study, seg_name)
    assert all(np.array_equal(read(f), p) for f, p in zip(frames[:4], fresh))
    dmodel = depth.load_model(tiny_study.perception.depth[0], predictions.model_dir(tiny_study, d_name) / "model.pt")
    dfresh = depth.predict(dmodel, np.stack([f.rgb for f in frames[:4]]), amp=tiny_study.perception.amp)
    dread = predictions.depth_source(tiny_study, d_name)
    assert all(np.allclose(dread(f), p, rtol=1e-5) for f, p in zip(frames[:4], dfresh))
    # the degenerate test frames (all-NaN depth, no labelled pixel) read fine from every source
    nan_frame, unlabelled = sel.test[0], sel.test[1]
    assert np.isnan(predictions.depth_source(tiny_study, "gt")(nan_frame)).all()
    assert (predictions.semantic_source(tiny_study, "gt")(unlabelled) == -1).all()
    for f in (nan_frame, unlabelled):
        assert np.isfinite(dread(f)).all() and read(f).shape == (H, W)
    # a missing prediction is one clear error naming the file
    path = predictions.prediction_path(tiny_study, seg_name, frames[0])
    path.unlink()
    with pytest.raises(predictions.PredictionsMissing, match=rf"'{seg_name}'.*{path.name}.*monolib perception"):
        read(frames[0])
    io.write_h5(path, fresh[0])
    # a second run does no work: status cached, no file touched
    files = sorted(p for p in paths.RUNS.rglob("*") if p.is_file()) + sorted(paths.FIGURES.rglob("*.csv"))
    before = {p: os.stat(p).st_mtime_ns for p in files}
    again = predictions.run(tiny_study, progress=False)
    assert set(again.attrs["status"].values()) == {"cached"}
    assert {p: os.stat(p).st_mtime_ns for p in files} == before
    # a GCN / scenario / threshold change keeps the cache keys
    keys = [predictions.model_key(tiny_study, n) for n in tiny_study.model_names()]
    tiny_study.gcn.epochs, tiny_study.thresholds = 99, [3.0]
    assert keys == [predictions.model_key(tiny_study, n) for n in tiny_study.model_names()]


def _png_is_a_picture(path: Path, min_size: tuple[int, int]) -> np.ndarray:
    """The PNG as an (H, W, 3) array, after checking it is at least `min_size` (w, h) and not blank."""
    from PIL import Image

    with Image.open(path) as im:
        assert im.format == "PNG" and im.size[0] >= min_size[0] and im.size[1] >= min_size[1], (path, im.size)
        rgb = np.asarray(im.convert("RGB"))
    colours = len(np.unique(rgb.reshape(-1, 3), axis=0))
    assert colours > 50 and (rgb < 250).any(axis=2).mean() > 0.05, (path, colours)  # drawn on, not a white page
    return rgb


@pytest.mark.slow
def test_figures(tiny_study):
    """Each figure is a real picture (a PNG of a sensible size, not blank), and draws the study's data: the training
    curves of every trained model, and Figures 3 and 4 the test frames, their ground truth and the predictions."""
    import matplotlib

    matplotlib.use("agg")
    import matplotlib.pyplot as plt

    from monolib.data.labels import colourize
    from monolib.perception import depth, predictions
    from monolib.report import perception_figures

    predictions.run(tiny_study, progress=False)
    fig_dir = paths.figures_dir("smoke")
    depth_models = [d.name for d in tiny_study.perception.depth]
    frames = perception_figures._test_frames(tiny_study, 3)
    assert len(frames) == 3

    fig = perception_figures.plot_training(tiny_study)
    _png_is_a_picture(fig_dir / "perception_training.png", (500, 200))
    loss, metric = fig.axes
    assert (loss.get_title(), metric.get_title()) == ("training loss", "validation metric")
    assert [line.get_label() for line in loss.lines] == tiny_study.model_names()
    for line, name in zip(loss.lines, tiny_study.model_names()):
        h = io.read_json(predictions.model_dir(tiny_study, name) / "history.json")["epochs"]
        assert list(line.get_xdata()) == [r["epoch"] for r in h]
        assert list(line.get_ydata()) == pytest.approx([r["train_loss"] for r in h])
    assert [line.get_label() for line in metric.lines] == [f"{tiny_study.perception.segmentation.name} (mIoU)"] + \
        [f"{n} (delta<1.25)" for n in depth_models]
    plt.close(fig)

    fig = perception_figures.plot_depth_examples(tiny_study)
    _png_is_a_picture(fig_dir / "fig3_depth.png", (500, 200))
    ncol = 1 + 2 * (1 + len(depth_models))                    # RGB, then GT + each model in metres and 0..1
    assert len(fig.axes) == 3 * ncol
    assert [a.get_title() for a in fig.axes[:ncol]] == ["RGB"] + [f"{m} (m)" for m in ["ground truth"] + depth_models] \
        + [f"{m} (0..1)" for m in ["ground truth"] + depth_models]
    d_name = depth_models[0]
    model = depth.load_model(tiny_study.perception.depth[0], predictions.model_dir(tiny_study, d_name) / "model.pt")
    for r, f in enumerate(frames):
        row = fig.axes[r * ncol : (r + 1) * ncol]
        np.testing.assert_array_equal(row[0].images[0].get_array(), f.rgb)
        np.testing.assert_array_equal(np.ma.filled(row[1].images[0].get_array(), np.nan), f.depth.astype(np.float32))
        np.testing.assert_allclose(np.asarray(row[2].images[0].get_array()),
                                   depth.predict(model, f.rgb[None], amp=tiny_study.perception.amp)[0], rtol=1e-4)
        assert f.setting in row[0].get_ylabel()
    plt.close(fig)

    fig = perception_figures.plot_semantic_examples(tiny_study)
    _png_is_a_picture(fig_dir / "fig4_semantics.png", (400, 300))
    assert len(fig.axes) == 3 * 3
    assert [a.get_title() for a in fig.axes[:3]] == ["RGB", "ground truth",
                                                      f"DeepLabV3 ({tiny_study.perception.segmentation.name})"]
    pred = predictions.semantic_source(tiny_study, tiny_study.perception.segmentation.name)
    for r, f in enumerate(frames):
        rgb, gt, pr = (a.images[0].get_array() for a in fig.axes[3 * r : 3 * r + 3])
        np.testing.assert_array_equal(rgb, f.rgb)
        np.testing.assert_array_equal(gt, colourize(f.semantic))
        np.testing.assert_array_equal(pr, colourize(pred(f)))
    plt.close(fig)


def test_pretrained_offline_error(tiny_study, monkeypatch, tmp_path):
    from monolib.perception import segmentation

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    spec = tiny_study.perception.segmentation
    spec.pretrained = True
    with pytest.raises(segmentation.PretrainedUnavailable, match="unavailable offline"):
        segmentation.build_model(spec)


def test_leres_structure_loads_its_own_keys(tmp_path):
    """A checkpoint in AdelaiDepth's layout ({'depth_model': {'module.depth_model.*': ...}}) loads strictly."""
    from monolib.perception import depth

    torch.manual_seed(0)
    src = depth.LeReSDepthModel("resnet18", 16, "leres", None, (64, 64))
    ckpt = {"depth_model": {f"module.depth_model.{k}": v for k, v in src.state_dict().items()}}
    torch.save(ckpt, tmp_path / "res.pth")
    dst = depth.LeReSDepthModel("resnet18", 16, "leres", None, (64, 64))
    depth.load_adelai_checkpoint(dst, tmp_path / "res.pth")
    assert all(torch.equal(a, b) for a, b in zip(src.state_dict().values(), dst.state_dict().values()))
    bad = depth.LeReSDepthModel("resnet18", 32, "leres", None, (64, 64))
    with pytest.raises(ValueError, match="does not match"):
        depth.load_adelai_checkpoint(bad, tmp_path / "res.pth")


# ---- prediction over the dataset: DataLoader, batches, restart -------------------------------------------------

def _untrained(study):
    """The study's segmentation net and first depth net, seeded, untrained: [(name, task, model)]. Their BatchNorm
    statistics are those of the study's frames (one forward pass), so that different frames predict differently."""
    from monolib.perception import depth, segmentation

    torch.manual_seed(0)
    nets = [(study.perception.segmentation.name, "segmentation",
             segmentation.build_model(study.perception.segmentation))]
    nets += [(d.name, "depth", depth.build_model(d)) for d in study.perception.depth[:1]]
    x = segmentation.normalise(segmentation.to_batch([f.rgb for f in _frames(study).train[::3]]))
    for _, _, model in nets:
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.reset_running_stats()
                m.momentum = None  # the statistics of this one pass
        with torch.no_grad():
            model.train()(x)
    return [(name, task, model.eval()) for name, task, model in nets]


def _read_predictions(study, name, frames):
    return [io.read_h5(perception_path(study, name, f)) for f in frames]


def perception_path(study, name, frame):
    from monolib.perception import predictions

    return predictions.prediction_path(study, name, frame)


@pytest.mark.slow
def test_loader_workers_change_no_prediction(tiny_study):
    """Frames read by 2 worker processes give the predictions of frames read in the main process, bit for bit, each
    written to its own frame's file (36 frames in batches of 5: a last batch of 1)."""
    from monolib.perception import predictions

    torch.set_num_threads(1)
    frames = _frames(tiny_study).all()
    tiny_study.perception.predict_batch = 5
    for name, task, model in _untrained(tiny_study):
        tiny_study.perception.loader_workers = 0
        assert predictions._predict_all(tiny_study, name, model, frames, progress=False)[:2] == (len(frames),) * 2
        in_main = _read_predictions(tiny_study, name, frames)
        for f in frames:
            perception_path(tiny_study, name, f).unlink()
        tiny_study.perception.loader_workers = 2
        assert predictions._predict_all(tiny_study, name, model, frames, progress=False)[:2] == (len(frames),) * 2
        in_workers = _read_predictions(tiny_study, name, frames)
        assert len({p.tobytes() for p in in_main}) > 1  # different frames, different predictions
        assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(in_main, in_workers)), name
        assert_each_frame_has_its_own_prediction(task, model, frames, in_workers)


def test_the_passes_read_each_frame_once_and_predict_the_same(tiny_study, monkeypatch):
    """A `FrameRgb` shared by the stage's passes reads each frame's RGB once for all of them, and every network
    predicts from it what it predicts from the files read by its own pass, bit for bit; frames that do not fit in
    its memory are read again by every pass (and batched the same). Reads counted in the main process (0 loader
    workers); `test_loader_workers_change_no_prediction` holds the workers' side."""
    from monolib.perception import images, predictions

    torch.set_num_threads(1)
    frames = _frames(tiny_study).all()
    tiny_study.perception.predict_batch = 5
    tiny_study.perception.loader_workers = 0
    reads = []
    read = images.FrameImages.__getitem__
    monkeypatch.setattr(images.FrameImages, "__getitem__", lambda self, i: reads.append(i) or read(self, i))
    shared = images.FrameRgb(0)
    nets = _untrained(tiny_study)
    for name, task, model in nets:
        assert predictions._predict_all(tiny_study, name, model, frames, progress=False)[:2] == (len(frames),) * 2
        from_files = _read_predictions(tiny_study, name, frames)
        for f in frames:
            perception_path(tiny_study, name, f).unlink()
        assert predictions._predict_all(tiny_study, name, model, frames, progress=False,
                                       rgb=shared)[:2] == (len(frames),) * 2
        held = _read_predictions(tiny_study, name, frames)
        assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(from_files, held)), name
    assert len(reads) == len(nets) * len(frames) + len(frames)  # each pass from the files, and the shared read once
    assert shared.held.shape == (len(frames), *frames[0].rgb.shape) and shared.held.dtype == np.uint8

    reads.clear()
    small = images.FrameRgb(0, hold_bytes=(len(frames) - 1) * frames[0].rgb.nbytes)
    batches = [[b.numpy() for b in small.batches(frames, 5, torch.device("cpu"))] for _ in range(2)]
    assert len(reads) == 2 * len(frames) and small.held is None
    expect = [shared.held[i : i + 5] for i in range(0, len(frames), 5)]
    for got in batches:
        assert len(got) == len(expect) and all(np.array_equal(a, b) for a, b in zip(got, expect))
    reads.clear()
    assert [b.numpy().tobytes() for b in shared.batches(frames[3:9], 4, torch.device("cpu"))] == \
        [shared.held[3:7].tobytes(), shared.held[7:9].tobytes()] and not reads  # any run of the held frames


def test_a_missing_colour_file_is_one_error_naming_it(tiny_study, tmp_path):
    """A frame whose colour file is gone: one `DataFileError` naming the file and what its RGB was read for,
    whether its pass holds the frames or reads them batch by batch."""
    import shutil

    from monolib.io import DataFileError
    from monolib.perception import images

    root = tmp_path / "dataset"
    shutil.copytree(tiny_study.dataset_root, root)
    tiny_study.dataset.root = str(root)
    frames = _frames(tiny_study).test[:6]
    gone = frames[4].files["color"]
    gone.unlink()
    for hold in (images.HOLD_BYTES, 0):
        with pytest.raises(DataFileError, match=rf"{gone}: file not found \(the RGB of the test\)"):
            list(images.FrameRgb(0, hold).batches(frames, 4, torch.device("cpu"), "the RGB of the test"))


def assert_each_frame_has_its_own_prediction(task, model, frames, stored):
    """Each stored prediction is the model's prediction of that frame alone (a batch of one: equal up to the last
    bits that a batch's size moves on the CPU), and not another frame's: a prediction written to the wrong frame's
    file, after the first batch or anywhere, fails here."""
    from monolib.perception import depth, segmentation

    predict = segmentation.predict if task == "segmentation" else depth.predict
    for i, (f, got) in enumerate(zip(frames, stored)):
        alone = predict(model, np.stack([f.rgb]), 1)[0]
        if task == "segmentation":
            assert np.mean(alone == got) > 0.999, (task, i)
        else:
            assert np.allclose(alone, got, rtol=1e-4, atol=1e-5), (task, i, float(np.abs(alone - got).max()))
        others = [j for j in range(len(frames)) if not np.array_equal(stored[j], got)]
        assert others, (task, i)  # (every frame differs from some other: the comparison can tell them apart)


def test_a_stopped_run_predicts_only_the_missing_frames(tiny_study, monkeypatch):
    """A run stopped after 7 files keeps them; the next run writes only the other frames' files, runs the network on
    their batches only (the 2nd batch of 4, partly written, again: the same batches as an uninterrupted run), touches
    no file already written, and ends with the predictions of an uninterrupted run, bit for bit."""
    from monolib.perception import predictions

    torch.set_num_threads(1)
    frames = _frames(tiny_study).all()
    tiny_study.perception.predict_batch, tiny_study.perception.loader_workers = 4, 2
    name, task, model = _untrained(tiny_study)[1]
    predictions._predict_all(tiny_study, name, model, frames, progress=False)
    whole = _read_predictions(tiny_study, name, frames)
    for f in frames:
        perception_path(tiny_study, name, f).unlink()

    write_h5, written = io.write_h5, []

    def write_then_stop(path, array, *args, **kwargs):
        if len(written) == 7:
            raise KeyboardInterrupt("stopped")
        write_h5(path, array, *args, **kwargs)
        written.append(Path(path))

    monkeypatch.setattr(io, "write_h5", write_then_stop)
    with pytest.raises(KeyboardInterrupt):
        predictions._predict_all(tiny_study, name, model, frames, progress=False)
    monkeypatch.setattr(io, "write_h5", write_h5)
    assert [p for p in (perception_path(tiny_study, name, f) for f in frames) if p.is_file()] == written
    before = {p: os.stat(p).st_mtime_ns for p in written}
    n, through_the_net, _ = predictions._predict_all(tiny_study, name, model, frames, progress=False)
    assert (n, through_the_net) == (len(frames) - 7, len(frames) - 4)
    assert {p: os.stat(p).st_mtime_ns for p in written} == before
    assert all(np.array_equal(a, b) for a, b in zip(whole, _read_predictions(tiny_study, name, frames)))
    assert predictions._predict_all(tiny_study, name, model, frames, progress=False) == (0, 0, 0.0)


def test_predict_takes_a_tensor_batch_as_it_takes_numpy(tiny_study):
    """The DataLoader's uint8 (N, H, W, 3) tensor batch and the numpy array of the same frames predict the same, bit
    for bit; an image in another layout is one clear error."""
    from monolib.perception import depth, images, segmentation

    torch.set_num_threads(1)
    frames = _frames(tiny_study).test[:5]
    rgb = np.stack([f.rgb for f in frames])
    batch = next(iter(images.image_loader(frames, tiny_study.perception.predict_batch, 2, torch.device("cpu"))))
    assert batch.dtype == torch.uint8 and tuple(batch.shape) == rgb.shape and np.array_equal(batch.numpy(), rgb)
    for name, task, model in _untrained(tiny_study):
        predict = segmentation.predict if task == "segmentation" else depth.predict
        a, b = predict(model, rgb, 2), predict(model, batch, 2)
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b), name
        assert np.array_equal(predict(model, rgb[0], 2), predict(model, batch[:1], 2))  # one (H, W, 3) image
    with pytest.raises(ValueError, match=r"expected uint8 images \(N, H, W, 3\)"):
        segmentation.predict(model, batch.permute(0, 3, 1, 2))
    with pytest.raises(ValueError, match="expected uint8 images"):
        segmentation.predict(model, batch.float())


def test_float16_only_on_cuda_and_in_the_key_only_there(tiny_study, monkeypatch):
    """`amp` is float16 autocast on CUDA, float32 on the CPU; it enters the model's key only on CUDA (the CPU's
    predictions, and its keys, do not depend on it). The loader workers are never in the key; the batch always is
    (a prediction's last bits depend on it on the CPU)."""
    import monolib.device
    from monolib.perception import predictions, segmentation

    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert not isinstance(segmentation.precision(cpu, True), torch.autocast)
    assert not isinstance(segmentation.precision(cuda, False), torch.autocast)
    with pytest.warns(UserWarning, match="CUDA is not available") if not torch.cuda.is_available() else _nothing():
        ctx = segmentation.precision(cuda, True)
    assert isinstance(ctx, torch.autocast) and ctx.device == "cuda" and ctx.fast_dtype == torch.float16
    # on the device of the data: copied as (N, H, W, 3), laid out channels-first there
    x = segmentation.on_device(torch.zeros((2, 6, 8, 3), dtype=torch.uint8), torch.device("meta"))
    assert x.device.type == "meta" and tuple(x.shape) == (2, 3, 6, 8) and x.is_contiguous()

    name = tiny_study.perception.segmentation.name
    spec = tiny_study.perception

    def keys(dev):
        monkeypatch.setattr(monolib.device, "device", lambda: dev)
        out = []
        for amp, batch, workers in [(True, 8, 2), (False, 8, 2), (True, 8, 0), (True, 3, 2)]:
            spec.amp, spec.predict_batch, spec.loader_workers = amp, batch, workers
            out.append(predictions.model_key(tiny_study, name))
        return out

    on_cpu, on_cuda = keys(cpu), keys(cuda)
    assert on_cpu[0] == on_cpu[1] == on_cpu[2] != on_cpu[3]
    assert on_cuda[0] != on_cuda[1] and on_cuda[0] == on_cuda[2] != on_cuda[3] and on_cuda[1] != on_cpu[1]


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.mark.parametrize("change, message", [
    ({"loader_workers": -1}, "perception.loader_workers: expected 0 .* got -1"),
    ({"predict_batch": 0}, "perception.predict_batch: expected at least 1 .* got 0"),
    ({"amp": "yes"}, "perception.amp: expected true or false, got 'yes'"),
    ({"amp": 1}, "perception.amp: expected true or false, got 1"),
    ({"loader_workers": 1.5}, "perception.loader_workers: expected an integer"),
    ({"predict_batches": 4}, "perception.predict_batches: unknown key"),
])
def test_bad_prediction_keys_name_the_key(tmp_path, change, message):
    import yaml

    from monolib.params import StudyError

    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["perception"].update(change)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(StudyError, match=message):
        load_study(p)


def test_prediction_keys_default_to_the_batch_of_before():
    spec = load_study("smoke").perception
    assert (spec.predict_batch, spec.loader_workers, spec.amp) == (8, 2, True)


def test_a_depth_network_predicting_nan_is_an_error_not_a_cached_model(tiny_study, monkeypatch):
    """A depth network whose predictions are NaN for 90% of the pixels: its abs_rel on the other 10% could look
    good, so the stage stops with one error naming it, and nothing marks it done (no metrics, no `_complete`);
    a sound network's share (0) is in the perception table."""
    from monolib.perception import depth, predictions

    name = tiny_study.perception.depth[0].name
    real = depth.predict

    def mostly_nan(model, rgb, *args, **kwargs):
        out = real(model, rgb, *args, **kwargs)
        out[:, : int(0.9 * out.shape[1])] = np.nan
        return out

    monkeypatch.setattr(depth, "predict", mostly_nan)
    with pytest.raises(predictions.NonFiniteDepth, match=rf"perception model '{name}'.*8\d\.\d+% of its predicted "
                                                        r"test pixels are NaN or inf"):
        predictions.run(tiny_study, progress=False, only=[name])
    assert not (predictions.model_dir(tiny_study, name) / "metrics.json").exists()
    assert not (predictions.predictions_dir(tiny_study, name) / "_complete.json").exists()
    monkeypatch.setattr(depth, "predict", real)
    for f in predictions.predictions_dir(tiny_study, name).rglob("*.hdf5"):
        f.unlink()
    table = predictions.run(tiny_study, progress=False, only=[name])
    share = table[(table.model == name) & (table.metric == "nonfinite_share")]["value"]
    assert len(share) == 1 and share.iloc[0] == 0.0
