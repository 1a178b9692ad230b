"""Image-only baselines on the smoke dataset: shapes, determinism, black images, and a triplet CNN that learns."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from monolib import methods
from monolib.data.selection import Selection, select_frames
from monolib.data.dataset import ensure_dataset
from monolib.params import load_study
from monolib.retrieval import baselines
from monolib.retrieval.training import training_rule

IMAGE_METHODS = ["color_hist", "orb_bow", "image_triplet"]


@pytest.fixture(scope="module")
def smoke():
    study = load_study("smoke")
    sel = select_frames(study, ensure_dataset(study, progress=False), study.gcn.val_settings)
    for f in sel.all():  # read every image once (cached on the frame)
        f.rgb
    return study, sel


@pytest.fixture(scope="module")
def embeddings(smoke):
    study, sel = smoke
    return {m: baselines.embed(m, study, sel, 0) for m in IMAGE_METHODS}


def test_registered_as_image_methods():
    for m in IMAGE_METHODS:
        assert methods.kind(m) == "image"


@pytest.mark.parametrize("method", IMAGE_METHODS)
def test_embeddings_are_finite_float32_rows_of_the_test_frames(smoke, embeddings, method):
    _, sel = smoke
    emb, extra, history, _ = embeddings[method]
    assert emb.dtype == np.float32 and emb.ndim == 2 and emb.shape[0] == len(sel.test) and emb.shape[1] > 0
    assert np.isfinite(emb).all()
    assert isinstance(extra, dict)
    if history is not None:
        assert {"epoch", "train_loss", "val_loss", "val_recall@1"} <= set(history.columns)


@pytest.mark.parametrize("method", ["orb_bow", "image_triplet"])
def test_same_seed_same_embeddings(smoke, embeddings, method):
    study, sel = smoke
    again = baselines.embed(method, study, sel, 0)[0]
    np.testing.assert_array_equal(embeddings[method][0], again)


def test_orb_bow_rows_are_unit_or_zero(smoke, embeddings):
    """A row is the L2-normalised tf-idf histogram of the image's ORB words: unit length exactly when the image has
    keypoints, zero when it has none (a flat grey image)."""
    study, sel = smoke
    emb, extra, _, _ = embeddings["orb_bow"]
    has_keypoints = np.array([len(baselines.orb_descriptors(f.rgb)) > 0 for f in sel.test])
    assert has_keypoints.mean() > 0.9  # the rendered rooms are textured: nearly every row must be a unit vector
    norms = np.linalg.norm(emb, axis=1)
    np.testing.assert_allclose(norms[has_keypoints], 1.0, atol=1e-5)
    assert (emb[~has_keypoints] == 0).all() and extra["test_no_keypoints"] == int((~has_keypoints).sum())
    assert (emb >= 0).all() and len({r.tobytes() for r in emb[has_keypoints]}) == int(has_keypoints.sum())
    # a flat grey image (no keypoint) and a textured one (many), beside a test frame, with the same vocabulary
    grey = np.full((96, 128, 3), 128, np.uint8)
    rng = np.random.default_rng(0)
    textured = np.kron(rng.integers(0, 256, (12, 16, 3)), np.ones((8, 8, 1))).astype(np.uint8)  # 8-px random tiles
    assert len(baselines.orb_descriptors(grey)) == 0 and len(baselines.orb_descriptors(textured)) > 50
    frames = [SimpleNamespace(rgb=grey, setting=sel.test[0].setting, key="grey"),
              SimpleNamespace(rgb=textured, setting=sel.test[0].setting, key="textured"), sel.test[0]]
    e, x, _, _ = baselines.embed("orb_bow", study, Selection(sel.train, sel.val, frames), 0)
    assert (e[0] == 0).all() and x["test_no_keypoints"] == 1
    assert np.linalg.norm(e[1]) == pytest.approx(1.0, abs=1e-5) and (e[1] > 0).sum() > 1
    np.testing.assert_allclose(e[2], emb[0], atol=1e-6)   # a test frame describes the same in any company
    assert not np.allclose(e[1], e[2])


def test_black_image_does_not_crash(smoke):
    study, sel = smoke
    black = np.zeros((96, 128, 3), np.uint8)
    assert np.isfinite(baselines.color_hist(black)).all()
    assert baselines.orb_descriptors(black).shape == (0, 256)
    dark = SimpleNamespace(rgb=black, setting=sel.test[0].setting, key="dark")
    emb, extra, _, _ = baselines.embed("orb_bow", study, Selection(sel.train, sel.val, [dark] + sel.test[:3]), 0)
    assert emb.shape[0] == 4 and np.isfinite(emb).all()
    assert (emb[0] == 0).all() and extra["test_no_keypoints"] >= 1
    emb = baselines.embed("color_hist", study, Selection(sel.train, sel.val, [dark]), 0)[0]
    assert np.isfinite(emb).all()


def test_triplet_cnn_training_loss_falls(smoke):
    study, sel = smoke
    rule = training_rule(dataclasses.replace(study.gcn, epochs=4, patience=4))
    _, extra, history, state = baselines.image_triplet_embed(study, sel, 0, rule=rule)
    loss = history["train_loss"].tolist()
    assert len(loss) == 4 and extra["epochs_run"] == 4 and state
    assert min(loss[1:]) < 0.8 * loss[0]


def test_an_image_baseline_cell_evaluates_both_protocols(smoke, tmp_path):
    """An image method's cell: one embedding of the test frames, evaluated on `paper` and `siblings`."""
    import math

    import pandas as pd

    from monolib.report import results
    from monolib.retrieval import cell

    study, sel = smoke
    rec = cell.run_cell(study, "color_hist", "rgb", math.inf, 0, out_dir=str(tmp_path / "cell"))
    assert list(rec["metrics"]) == ["paper", "siblings"]
    rankings = pd.read_csv(tmp_path / "cell" / "rankings.csv")
    protocol = pd.read_csv(tmp_path / "cell" / "protocol.csv")
    counts = results.check_protocols(rankings, protocol, study.protocol.positives,
                                    {"paper": study.protocol.settings, "siblings": 2 * study.protocol.siblings})
    assert counts["paper"]["queries"] == study.protocol.settings * study.protocol.queries
    for name, r in results.split_protocols(rankings).items():
        assert results.recompute_metrics(r, [1, 5, 10], [2, 4, 6]) == pytest.approx(rec["metrics"][name])
    assert np.load(tmp_path / "cell" / "embeddings.npy").shape[0] == len(sel.test)


def test_a_frames_image_descriptor_is_computed_once_per_colour_file(tmp_path):
    """`per_frame` (what the seeds of one baseline share in a warm kernel): the value of a real Hypersim-layout
    frame's image, computed once per colour file, and computed again once the file is rewritten."""
    from hypersim_files import write_setting

    from monolib.data.hypersim import HypersimDataset
    from monolib.io import read_h5, write_h5

    write_setting(tmp_path, "ai_001_001", frames=1)
    frame = HypersimDataset(tmp_path).frame("ai_001_001", "cam_00", 0)
    calls = []

    def describe(rgb):
        calls.append(1)
        return baselines.color_hist(rgb)

    first = baselines.per_frame(frame, "test_hist", describe)
    np.testing.assert_array_equal(first, baselines.color_hist(frame.rgb))
    assert baselines.per_frame(frame, "test_hist", describe) is first and len(calls) == 1
    colour = read_h5(frame.files["color"])
    write_h5(frame.files["color"], (colour * 0.5).astype(colour.dtype))  # a new file, same path
    again = HypersimDataset(tmp_path).frame("ai_001_001", "cam_00", 0)
    baselines.per_frame(again, "test_hist", describe)
    assert len(calls) == 2
