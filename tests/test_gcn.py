"""The encoder: empty graphs, deterministic training, and a triplet loss that falls on separable settings."""
import math

import numpy as np
import pytest
import torch

from monolib.gcn import GraphEncoder, draw_triplets, embed, train
from monolib.params import GCNSpec
from monolib.graph import at_threshold, complete_graph


def toy_graphs(n_settings=4, per=6, seed=0):
    """Settings differ by which labels they hold; frames jitter positions and colours."""
    rng = np.random.default_rng(seed)
    graphs = []
    for s in range(n_settings):
        labels = np.array([1, 2] + [3 + s, 10 + 2 * s])
        for i in range(per):
            colour = np.full((len(labels), 3), s / n_settings) + rng.normal(0, 0.02, (len(labels), 3))
            x = np.column_stack([labels, colour]).astype(np.float32)
            pos = rng.normal(size=(len(labels), 3)).astype(np.float32)
            graphs.append(at_threshold(complete_graph(x, pos, f"ai_900_{s:03d}", f"ai_900_{s:03d}/cam_00/{i:04d}"), 1.5))
    return graphs


def test_empty_and_one_node_graphs_embed_to_finite_vectors():
    spec = GCNSpec(epochs=1)
    model = GraphEncoder(spec)
    empty = at_threshold(complete_graph(np.zeros((0, 4)), np.zeros((0, 3)), "a", "a/0"), math.inf)
    one = at_threshold(complete_graph(np.ones((1, 4)), np.zeros((1, 3)), "b", "b/0"), math.inf)
    z = embed(model, [empty, one, empty])
    assert z.shape == (3, 64) and torch.isfinite(z).all()
    assert (z[0] == 0).all()


def test_triplets_respect_settings():
    s = np.array(["a"] * 3 + ["b"] * 2 + ["c"])
    a, p, n = draw_triplets(s, np.random.default_rng(0))
    assert sorted(a) == list(range(6))
    assert (s[a] == s[p]).all() and (s[a] != s[n]).all()


def test_training_lowers_the_loss_and_is_deterministic():
    graphs = toy_graphs()
    spec = GCNSpec(epochs=15, batch_size=8, patience=100, lr=1e-3)
    r1 = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    losses = [h["train_loss"] for h in r1.history]
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:3])
    r2 = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    assert [h["train_loss"] for h in r2.history] == pytest.approx(losses)
    torch.testing.assert_close(embed(r1.model, graphs), embed(r2.model, graphs))


@pytest.mark.parametrize("choice", [
    {"edges": "upper", "linear": False},
    {"label": "embedding", "colour": "standardised"},
    {"label": "onehot"},
    {"edge_weight": "inverse"},
    {"conv": "gine"},
    {"conv": "gatv2"},
    {"pooling": "meanmax"},
    {"mining": "batch_hard"},
])
@pytest.mark.parametrize("threshold", [1.5, 0.0])
def test_every_encoder_variant_trains_and_embeds(choice, threshold):
    """... at a threshold, and at 0 (no edges: the encoder sees the nodes only)."""
    import dataclasses

    spec = dataclasses.replace(GCNSpec(epochs=2, batch_size=8, patience=5), **choice)
    graphs = toy_graphs()
    graphs = [at_threshold(complete_graph(g.x, g.pos, g.setting, g.frame), threshold, spec.edges == "both")
              for g in graphs]
    assert (threshold == 0) == all(g.edge_index.shape[1] == 0 for g in graphs)
    empty = at_threshold(complete_graph(np.zeros((0, 4)), np.zeros((0, 3)), "ai_900_009", "e"), threshold)
    result = train(graphs[:18], graphs[18:], spec, seed=0, threads=1)
    z = embed(result.model, graphs + [empty])
    assert z.shape == (len(graphs) + 1, result.model.out_channels) and torch.isfinite(z).all()
    assert all(np.isfinite(h["train_loss"]) for h in result.history)
