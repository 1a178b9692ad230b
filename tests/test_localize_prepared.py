"""The localizer's networks prepared for queries (`inference.prepare_network`: BatchNorm folded into the convolutions,
the networks kept in evaluation mode) against the networks as the perception stage loads them, on real inputs: the
project's zoo networks (quick's DeepLabV3 and Lite0 depth, trained) on photographs (scikit-image's samples at the
study's 256 x 192); and the localizer's answers with and without the preparation, and its ranking against the
pandas one it replaced."""
import copy

import numpy as np
import pandas as pd
import pytest
import torch
from skimage import data as samples

from monolib import localize
from monolib.params import load_study
from monolib.perception import depth, inference, predictions, segmentation, weights

from tests.test_localize import image, make_database, weights as smoke_weights  # noqa: F401  (fixtures)

# Folding rounds each convolution's output otherwise (float32): an argmax whose two best logits nearly tie may flip.
# The bounds leave room for such ties and nothing more: on quick's test frames as photos, a few pixels in ten million.
MAX_CLASS_CHANGES = 0.001  # share of a frame's pixels
MAX_DEPTH_RELATIVE = 1e-4


@pytest.fixture(scope="module")
def photos() -> np.ndarray:
    """Three photographs at the study's size, as `Localizer.analyse` makes them (centre-cropped to 4:3)."""
    return np.stack([localize.to_study_frame(im, 256, 192)
                     for im in (samples.coffee(), samples.astronaut(), samples.chelsea())])


def zoo_network(name: str) -> torch.nn.Module:
    """Quick's zoo network `name`, as the localizer loads it before preparing it (`localize._load_network`)."""
    study = load_study("quick")
    spec, task = predictions._spec(study, name)
    net = weights.load(spec, task, spec.weights)
    return segmentation.for_inference(net).eval() if task == "segmentation" else net.eval()


def test_every_batchnorm_is_folded_and_the_networks_stay_as_they_were():
    for name in ("deeplab", "depth_lite0"):
        net = zoo_network(name)
        before = {k: v.clone() for k, v in net.state_dict().items()}
        bns = sum(isinstance(m, torch.nn.BatchNorm2d) for m in net.modules())
        pairs = inference.conv_batchnorm_pairs(net)
        assert len(pairs) == bns > 0, name
        prepared = inference.prepare_network(copy.deepcopy(net))
        assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in prepared.modules()), name
        assert all(torch.equal(v, before[k]) for k, v in net.state_dict().items())  # the original untouched
        # `predict`'s train()/eval() reach the wrapper only: the network stays in evaluation mode
        prepared.train()
        assert not any(m.training for m in prepared.net.modules())


def test_prepared_segmentation_gives_the_same_classes(photos):
    net = zoo_network("deeplab")
    plain = segmentation.predict(net, photos)
    fast = segmentation.predict(inference.prepare_network(copy.deepcopy(net)), photos)
    assert fast.dtype == plain.dtype and fast.shape == plain.shape == (3, 192, 256)
    assert len(np.unique(plain)) > 3  # a real input: several classes
    for a, b in zip(plain, fast):
        assert np.count_nonzero(a != b) <= MAX_CLASS_CHANGES * a.size
    # without folding the prepared network is the same computation: the same classes to the pixel
    np.testing.assert_array_equal(segmentation.predict(inference.prepare_network(copy.deepcopy(net), fold=False),
                                                       photos), plain)


def test_prepared_depth_gives_the_same_depth(photos):
    net = zoo_network("depth_lite0")
    plain = depth.predict(net, photos)
    fast = depth.predict(inference.prepare_network(copy.deepcopy(net)), photos)
    assert fast.shape == plain.shape == (3, 192, 256) and np.isfinite(plain).all() and plain.std() > 0.05
    np.testing.assert_allclose(fast, plain, rtol=MAX_DEPTH_RELATIVE, atol=0)
    np.testing.assert_array_equal(depth.predict(inference.prepare_network(copy.deepcopy(net), fold=False), photos),
                                  plain)


def test_the_localizer_answers_the_same_places_prepared_or_not(tmp_path, smoke_weights, image):  # noqa: F811
    db = make_database(tmp_path, smoke_weights)
    plain, fast = localize.Localizer.open(db, prepare=False), localize.Localizer.open(db)
    assert isinstance(fast.segmentation, inference.QueryNetwork) and isinstance(fast.depth, inference.QueryNetwork)
    rgb = plain.read(image)
    a, b = plain.analyse(rgb), fast.analyse(rgb)
    assert np.count_nonzero(a["semantic"] != b["semantic"]) <= MAX_CLASS_CHANGES * a["semantic"].size
    np.testing.assert_allclose(b["depth"], a["depth"], rtol=MAX_DEPTH_RELATIVE, atol=0)
    assert [m["place"] for m in plain.rank(a["embedding"], 4)] == [m["place"] for m in fast.rank(b["embedding"], 4)]
    assert localize.localize([str(image)], db, k=4) == [
        {"image": str(image), "matches": [{k: v for k, v in m.items() if k != "row"}
                                          for m in plain.rank(a["embedding"], 4)]}]
    # what only a figure draws is left out of `stages`, and is the same when asked for
    assert set(a) - set(fast.analyse(rgb, drawn=False)) == {"pixels", "edges"}
    torch.testing.assert_close(fast.stages(rgb), b["embedding"], rtol=0, atol=0)


def pandas_rank(loc: localize.Localizer, z: torch.Tensor, k: int) -> list[dict]:
    """`Localizer.rank` as it was written with pandas: sort by distance (stable), each place's first row, k."""
    d = torch.cdist(z[None].float(), loc.embeddings.float())[0].numpy()
    df = loc.frames.assign(distance=d, row=np.arange(len(d))).sort_values("distance", kind="stable")
    best = df.groupby("setting", sort=False).head(1).head(k)
    return [{"rank": i + 1, "place": r.setting, "distance": float(r.distance), "image": r.frame, "row": int(r.row)}
            for i, r in enumerate(best.itertuples())]


def test_rank_is_the_pandas_ranking_ties_included(tmp_path, smoke_weights):  # noqa: F811
    loc = localize.Localizer.open(make_database(tmp_path, smoke_weights, per_setting=5))
    rng = np.random.default_rng(1)
    emb = rng.normal(size=loc.embeddings.shape).astype(np.float32)
    emb[7] = emb[2]  # equal distances: the earlier row first
    emb[13] = emb[2]
    frames = loc.frames.sample(frac=1.0, random_state=0).reset_index(drop=True)  # places interleaved
    import dataclasses

    loc = dataclasses.replace(loc, embeddings=torch.from_numpy(emb), frames=frames)
    for z in [torch.from_numpy(emb[2]), *torch.from_numpy(rng.normal(size=(20, emb.shape[1])).astype(np.float32))]:
        for k in (1, 3, frames["setting"].nunique()):
            assert loc.rank(z, k) == pandas_rank(loc, z, k)
    empty = dataclasses.replace(loc, embeddings=torch.zeros(0, emb.shape[1]),
                                frames=pd.DataFrame({"frame": [], "setting": []}))
    assert empty.rank(torch.from_numpy(emb[0]), 3) == []
