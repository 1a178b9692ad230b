"""The layout encoder: layout features of nodes and edges worked out by hand in both projections, the
graphs the encoder reads (and the published graphs it cannot), negatives and batches drawn over families, the pair
readout, the new convolution and pooling, family mining in training, and the study keys that choose them."""
import dataclasses
import math

import numpy as np
import pytest
import torch
import yaml

from monolib import paths
from monolib.data.protocols import family
from monolib.graphs.build import (
    EDGE_LAYOUT, NODE_FEATURES, NODE_LAYOUT, at_threshold, complete_graph, edge_layout_features, layout_graph,
    node_layout_features,
)
from monolib.params import GCNSpec, StudyError, load_study
from monolib.retrieval import gcn, training

# the layout encoders keep `ours`'s undirected edges and linear head (params/quick.yaml)
SMALL = GCNSpec(hidden=16, layers=2, out=8, epochs=2, batch_size=16, patience=5, edges="both", linear=True)


def small(**choice) -> GCNSpec:
    return dataclasses.replace(SMALL, **choice)


# the same physical points in each projection's camera frame: monograph (x right, y down, z forward) and exact
# (x right, y up, z backward); a point (r, u, f) in right / up / forward metres is (r, -u, f) and (r, u, -f)
TO_FRAME = {"monograph": lambda ruf: ruf * np.array([1.0, -1.0, 1.0]),
            "exact": lambda ruf: ruf * np.array([1.0, 1.0, -1.0])}


def close(got: torch.Tensor, want) -> None:
    np.testing.assert_allclose(got.numpy(), np.asarray(want, dtype=np.float64), rtol=1e-5, atol=1e-5)


def labelled(n: int, colour: float = 0.5) -> np.ndarray:
    """x of `n` nodes: NYU40 ids 1..n and one grey."""
    return np.column_stack([np.arange(1, n + 1), np.full((n, 3), colour)]).astype(np.float32)


# --- 1. layout features by hand -----------------------------------------------------------------------------------

@pytest.mark.parametrize("projection", ["monograph", "exact"])
def test_edge_layout_features_by_hand(projection):
    """Node 1 is 2 m straight above node 0, node 2 is 3 m right of node 0 (level), node 3 sits on node 0. Each edge
    i -> j: its length, the rise of j above i along the camera's up, and the angle to up (0 above, pi below, pi / 2
    level or of zero length), in both directions of every pair."""
    ruf = np.array([[0.0, 0.0, 2.0], [0.0, 2.0, 2.0], [3.0, 0.0, 2.0], [0.0, 0.0, 2.0]])
    pos = TO_FRAME[projection](ruf)
    g = at_threshold(complete_graph(labelled(4), pos, "ai_001_001", "f"), math.inf)
    feats = edge_layout_features(g.pos, g.edge_index, g.edge_attr, projection)
    assert feats.shape == (12, EDGE_LAYOUT) and feats.dtype == torch.float32
    got = {(int(i), int(j)): f.tolist() for i, j, f in zip(g.edge_index[0], g.edge_index[1], feats)}
    s13 = math.sqrt(13.0)
    want = {
        (0, 1): [2.0, 2.0, 0.0], (1, 0): [2.0, -2.0, math.pi],                       # straight above / below
        (0, 2): [3.0, 0.0, math.pi / 2], (2, 0): [3.0, 0.0, math.pi / 2],            # level
        (0, 3): [0.0, 0.0, math.pi / 2], (3, 0): [0.0, 0.0, math.pi / 2],            # zero length
        (1, 2): [s13, -2.0, math.acos(-2.0 / s13)], (2, 1): [s13, 2.0, math.acos(2.0 / s13)],
        (1, 3): [2.0, -2.0, math.pi], (3, 1): [2.0, 2.0, 0.0],
        (2, 3): [3.0, 0.0, math.pi / 2], (3, 2): [3.0, 0.0, math.pi / 2],
    }
    assert set(got) == set(want)
    for edge, w in want.items():
        assert got[edge] == pytest.approx(w, abs=1e-5), (projection, edge)


def test_edge_layout_reads_the_lengths_it_is_given():
    """The first column is the graph's own edge attribute (published lengths are the truth of their graphs), not
    a length recomputed from the positions."""
    pos = torch.tensor([[0.0, 0.0, 2.0], [0.0, -1.0, 2.0]])
    ei = torch.tensor([[0], [1]])
    f = edge_layout_features(pos, ei, torch.tensor([[4.0]]), "monograph")
    close(f, [[4.0, 1.0, math.acos(0.25)]])


@pytest.mark.parametrize("projection", ["monograph", "exact"])
def test_node_layout_features_by_hand(projection):
    """Image column = right / forward, row = up / forward, log of the forward distance; forward clamped at 1 cm
    (a node on the camera or behind it)."""
    ruf = np.array([[1.0, 0.5, 2.0],      # right and above the axis, 2 m ahead
                    [-2.0, -1.0, 4.0],    # left and below, 4 m ahead
                    [0.3, 0.0, 0.001],    # 1 mm ahead: clamped to 1 cm
                    [0.0, 0.2, -3.0]])    # behind the camera: clamped to 1 cm
    pos = torch.as_tensor(TO_FRAME[projection](ruf), dtype=torch.float32)
    f = node_layout_features(pos, projection)
    assert f.shape == (4, NODE_LAYOUT)
    want = [[0.5, 0.25, math.log(2.0)],
            [-0.5, -0.25, math.log(4.0)],
            [30.0, 0.0, math.log(0.01)],
            [0.0, 20.0, math.log(0.01)]]
    for row, w in zip(f.tolist(), want):
        assert row == pytest.approx(w, rel=1e-5, abs=1e-5), projection


def test_the_two_projections_are_not_interchangeable():
    """The same coordinates read in the other projection are another scene: up and forward flip."""
    pos = torch.tensor([[1.0, 0.5, 2.0], [1.0, 1.5, 2.0]])
    mono, exact = node_layout_features(pos, "monograph"), node_layout_features(pos, "exact")
    assert mono[0].tolist() == pytest.approx([0.5, -0.25, math.log(2.0)])
    assert exact[0].tolist() == pytest.approx([100.0, 50.0, math.log(0.01)])
    ei, length = torch.tensor([[0], [1]]), torch.tensor([[1.0]])
    close(edge_layout_features(pos, ei, length, "monograph"), [[1.0, -1.0, math.pi]])
    close(edge_layout_features(pos, ei, length, "exact"), [[1.0, 1.0, 0.0]])


# --- 2. the graph the encoder reads -------------------------------------------------------------------------------

def published_like(n: int = 3):
    """A graph as `monolib.graphs.published` converts a published file: every pair and its length, no positions."""
    from torch_geometric.data import Data

    i, j = torch.triu_indices(n, n, offset=1)
    return Data(x=torch.as_tensor(labelled(n)), pair_index=torch.stack([i, j]),
                pair_len=torch.arange(1, len(i) + 1, dtype=torch.float32), setting="ai_001_002",
                frame="ai_001_002/cam_00/0007", num_nodes=n)


@pytest.mark.parametrize("flag", ["node_layout", "edge_layout"])
def test_published_graphs_have_no_layout(flag):
    g = published_like()
    with pytest.raises(ValueError, match=r"'ai_001_002/cam_00/0007'.*gcn\.node_layout, gcn\.edge_layout"):
        gcn.encoder_graph(g, math.inf, small(**{flag: True}), "monograph")
    plain = gcn.encoder_graph(g, math.inf, small(), "monograph")   # lengths only: what published graphs hold
    assert plain.x.shape == (3, NODE_FEATURES) and plain.edge_attr[:, 0].tolist() == [1.0, 2.0, 3.0] * 2


def test_layout_graph_adds_the_columns_asked_for():
    ruf = np.array([[0.0, 0.0, 2.0], [0.0, 1.0, 2.0], [4.0, 0.0, 2.0]])
    cached = complete_graph(labelled(3), TO_FRAME["exact"](ruf), "ai_001_001", "ai_001_001/cam_00/0000")
    plain = at_threshold(cached, 2.0)                                   # one pair closer than 2 m: (0, 1)
    assert layout_graph(plain, None, False, False) is plain             # nothing asked: the same graph
    assert gcn.encoder_graph(cached, 2.0, small(), "exact").edge_index.tolist() == plain.edge_index.tolist()

    nodes = gcn.encoder_graph(cached, 2.0, small(node_layout=True), "exact")
    assert nodes.x.shape == (3, NODE_FEATURES + 3)
    torch.testing.assert_close(nodes.x[:, :NODE_FEATURES], plain.x)
    close(nodes.x[:, NODE_FEATURES:], [[0.0, 0.0, math.log(2)], [0.0, 0.5, math.log(2)], [2.0, 0.0, math.log(2)]])
    torch.testing.assert_close(nodes.edge_attr, plain.edge_attr)       # lengths only
    assert plain.x.shape == (3, NODE_FEATURES)                          # the input graph is left as it was

    edges = gcn.encoder_graph(cached, 2.0, small(edge_layout=True), "exact")
    assert edges.edge_attr.shape == (2, 3) and edges.x.shape == (3, NODE_FEATURES)
    assert edges.edge_index.tolist() == [[0, 1], [1, 0]]
    close(edges.edge_attr, [[1.0, 1.0, 0.0], [1.0, -1.0, math.pi]])

    both = gcn.encoder_graph(cached, math.inf, small(node_layout=True, edge_layout=True, edges="upper"), "exact")
    assert both.x.shape == (3, 7) and both.edge_attr.shape == (3, 3)   # i < j only, as `edges: upper` says
    with pytest.raises(ValueError, match="projection: expected one of monograph, exact, got None"):
        layout_graph(plain, None, True, False)


def test_an_encoder_refuses_edge_attributes_of_another_width():
    ruf = np.array([[0.0, 0.0, 2.0], [0.0, 1.0, 2.0]])
    cached = complete_graph(labelled(2), TO_FRAME["monograph"](ruf), "ai_001_001", "f")
    three = gcn.encoder_graph(cached, math.inf, small(edge_layout=True), "monograph")
    with pytest.raises(ValueError, match="gcn.edge_layout: False"):
        gcn.embed(gcn.GraphEncoder(small(conv="gine")), [three])


# --- 3. negatives of the anchor's family --------------------------------------------------------------------------

def shuffled_settings(counts: dict, seed: int = 0) -> np.ndarray:
    s = np.concatenate([[name] * k for name, k in counts.items()])
    return s[np.random.default_rng(seed).permutation(len(s))]


COUNTS = {"ai_001_001": 3, "ai_001_002": 5, "ai_002_001": 4, "ai_002_002": 2, "ai_003_001": 3}


def test_family_negatives_take_the_sibling():
    s = shuffled_settings(COUNTS)
    _, _, negative = training.draw_triplets(s, np.random.default_rng(1))
    out = gcn.family_negatives(s, negative, 1.0, np.random.default_rng(2))
    assert out.shape == negative.shape and out is not negative
    sibling = {"ai_001_001": "ai_001_002", "ai_001_002": "ai_001_001", "ai_002_001": "ai_002_002",
               "ai_002_002": "ai_002_001"}
    for anchor, (setting, neg) in enumerate(zip(s, out)):
        if setting in sibling:
            assert s[neg] == sibling[setting], (anchor, setting, s[neg])
        else:                                                   # ai_003: a family of one setting
            assert neg == negative[anchor]
    np.testing.assert_array_equal(gcn.family_negatives(s, negative, 0.0, np.random.default_rng(2)), negative)
    np.testing.assert_array_equal(out, gcn.family_negatives(s, negative, 1.0, np.random.default_rng(2)))
    assert not np.array_equal(out, gcn.family_negatives(s, negative, 1.0, np.random.default_rng(3)))


def test_family_negatives_reach_every_other_setting_of_a_larger_family():
    """A family of three settings of unequal sizes: every graph of the two other settings is drawn (over seeds),
    never one of the anchor's own setting."""
    s = shuffled_settings({"ai_004_001": 2, "ai_004_002": 3, "ai_004_003": 4, "ai_005_001": 2, "ai_005_002": 2})
    drawn: dict[str, set] = {}
    for seed in range(60):
        out = gcn.family_negatives(s, np.full(len(s), -1), 1.0, np.random.default_rng(seed))
        assert (out >= 0).all() and (s[out] != s).all()
        assert all(family(a) == family(b) for a, b in zip(s, s[out]))
        for a, n in zip(s, out):
            drawn.setdefault(a, set()).add(int(n))
    for setting in np.unique(s):
        others = {i for i in range(len(s)) if family(s[i]) == family(setting) and s[i] != setting}
        assert drawn[setting] == others, setting


def test_family_share_is_the_share_of_anchors_redrawn():
    s = shuffled_settings({"ai_001_001": 250, "ai_001_002": 250, "ai_002_001": 250, "ai_002_002": 250})
    for share in (0.25, 0.5, 0.75):
        out = gcn.family_negatives(s, np.full(len(s), -1), share, np.random.default_rng(0))
        assert abs((out >= 0).mean() - share) < 0.05, share


# --- 4. batches of whole families ---------------------------------------------------------------------------------

def test_family_batches_hold_whole_families():
    counts = {"ai_001_001": 9, "ai_001_002": 7, "ai_002_001": 8, "ai_002_002": 2, "ai_003_001": 6,
              "ai_003_002": 10, "ai_004_001": 5, "ai_004_002": 6}
    s = shuffled_settings(counts)
    settings_of = {f: sorted(n for n in counts if family(n) == f) for f in {family(n) for n in counts}}
    batches = gcn.family_batches(s, 16, np.random.default_rng(0), per_setting=4)
    assert len(batches) == len(s) // 16                         # 2 families of 2 settings x 4 graphs per batch
    families_seen = set()
    for b in batches:
        fams = {family(n) for n in s[b]}
        assert len(fams) == 2
        families_seen |= fams
        assert len(b) == 4 * sum(len(settings_of[f]) for f in fams)
        for f in fams:
            for name in settings_of[f]:
                members = b[s[b] == name]
                assert len(members) == 4, (f, name)
                if counts[name] >= 4:                          # enough graphs: 4 different ones
                    assert len(set(members.tolist())) == 4
    assert len(families_seen) > 2                               # the families are drawn, not always the first two
    again = gcn.family_batches(s, 16, np.random.default_rng(0), per_setting=4)
    assert all(np.array_equal(a, b) for a, b in zip(batches, again)) and len(again) == len(batches)
    other = gcn.family_batches(s, 16, np.random.default_rng(1), per_setting=4)
    assert not all(np.array_equal(a, b) for a, b in zip(batches, other))
    wide = gcn.family_batches(s, 64, np.random.default_rng(0), per_setting=4)  # more families than exist: all 4
    assert all({family(n) for n in s[b]} == set(settings_of) for b in wide)


# --- 5. the pair readout and message passing ----------------------------------------------------------------------

def twins(**choices):
    """Encoders of the specs `choices` built from the same random state (the same weights where shapes agree)."""
    out = []
    for c in choices.values():
        torch.manual_seed(0)
        out.append(gcn.GraphEncoder(small(**c)).eval())
    return out


def scene(threshold: float, spec: GCNSpec = SMALL):
    """Four objects of four labels and greys, 2 to 4 m ahead, as the encoder of `spec` reads them at `threshold`."""
    ruf = np.array([[0.0, 0.0, 2.0], [0.5, 1.0, 2.5], [-1.0, 0.2, 3.0], [2.0, -0.5, 4.0]])
    x = labelled(4) + np.column_stack([np.zeros(4), np.linspace(0, 0.3, 4)[:, None].repeat(3, 1)]).astype(np.float32)
    return gcn.encoder_graph(complete_graph(x, TO_FRAME["monograph"](ruf), "ai_001_001", "f"), threshold, spec,
                             "monograph")


def test_pair_readout_width_and_no_edges():
    model, = twins(a=dict(pooling="meanmax", pair_readout=True))
    assert model.out_channels == 8 * 2 + 2 * 8
    z = gcn.embed(model, [scene(math.inf), scene(0.0)])
    assert z.shape == (2, 32) and torch.isfinite(z).all()
    assert (z[1, 16:] == 0).all() and (z[0, 16:] != 0).any()     # no edge: no pair


def test_pair_readout_is_the_mean_and_max_over_the_edges():
    model, = twins(a=dict(pair_readout=True))
    g = scene(math.inf)
    z = gcn.embed(model, [g])[0]
    with torch.no_grad():
        h = model.features(g.x)
        src, dst = g.edge_index
        m = model.pair_mlp(torch.cat([h[src], h[dst], g.edge_attr], dim=1))
    assert m.shape == (12, 8)
    torch.testing.assert_close(z[8:], torch.cat([m.mean(0), m.amax(0)]))


@pytest.mark.parametrize("conv", [dict(), dict(conv="gine", edge_layout=True), dict(conv="gatv2"),
                                  dict(conv="transformer", edge_layout=True, pooling="attention")])
def test_without_message_passing_only_the_pairs_see_the_edges(conv):
    """The same nodes with and without edges: the node part (pooled node embeddings) is the same without message
    passing and differs with it; the pair part differs; and without message passing the encoder is the message
    passing one (same weights) on a graph without edges."""
    alone, passing = twins(alone=dict(pair_readout=True, message_passing=False, **conv),
                           passing=dict(pair_readout=True, message_passing=True, **conv))
    k = alone.out_channels - 16                                     # the node part; then the pairs' mean and max
    edges, none = scene(math.inf, alone.spec), scene(0.0, alone.spec)
    assert edges.edge_index.shape[1] == 12 and none.edge_index.shape[1] == 0
    longer = edges.clone()                                          # the lengths (only) three times longer
    longer.edge_attr = edges.edge_attr.clone()
    longer.edge_attr[:, 0] *= 3.0
    za = gcn.embed(alone, [edges, none, longer])
    zp = gcn.embed(passing, [edges, none, longer])
    torch.testing.assert_close(za[0, :k], za[1, :k])
    torch.testing.assert_close(za[2, :k], za[1, :k])
    assert not torch.allclose(za[0, k:], za[1, k:])
    assert not torch.allclose(za[0, k:], za[2, k:])                # the pairs read the lengths
    assert not torch.allclose(zp[0, :k], zp[1, :k])
    torch.testing.assert_close(za[:, :k], zp[1:2, :k].expand(3, k))
    torch.testing.assert_close(za[0, k:], zp[0, k:])               # the pair readout reads the input features


@pytest.mark.parametrize("choice", [dict(pair_readout=True, pooling="meanmax"),
                                    dict(pair_readout=True, message_passing=False, edge_layout=True, node_layout=True),
                                    dict(conv="transformer", pooling="attention", edge_layout=True)])
def test_an_empty_graph_embeds_to_zeros(choice):
    model, = twins(a=choice)
    empty = gcn.encoder_graph(complete_graph(np.zeros((0, 4)), np.zeros((0, 3)), "ai_009_001", "e"), math.inf,
                              model.spec, "monograph")
    g = scene(2.0, model.spec)
    with torch.no_grad():
        z = model(gcn.GraphPool([empty, g, empty]).batch([0, 1, 2]))
    assert z.shape == (3, model.out_channels) and torch.isfinite(z).all()
    assert (z[0] == 0).all() and (z[2] == 0).all() and (z[1] != 0).any()
    torch.testing.assert_close(gcn.embed(model, [empty, g]), z[:2])


def test_the_layout_columns_are_standardised_on_the_training_graphs():
    """With raw colours (the paper's), the node layout columns and the edge layout are still standardised with the
    training set's mean and std (`set_colour_stats`); the label and colours pass as they are."""
    torch.manual_seed(0)
    spec = small(node_layout=True, edge_layout=True)
    model = gcn.GraphEncoder(spec)
    assert model.colour_mean.shape == (6,) and model.edge_mean.shape == (3,)
    graphs = [gcn.encoder_graph(g, 2.0, spec, "monograph") for g in family_graphs(per=3)]
    model.set_colour_stats(graphs)
    x = torch.cat([g.x for g in graphs])
    f = model.features(x)
    torch.testing.assert_close(f[:, :NODE_FEATURES], x[:, :NODE_FEATURES])
    torch.testing.assert_close(f[:, NODE_FEATURES:].mean(0), torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(f[:, NODE_FEATURES:].std(0), torch.ones(3), atol=1e-5, rtol=0)
    e = model.edge_features(gcn.GraphPool(graphs).batch(range(len(graphs))))
    assert e.shape == (sum(g.edge_index.shape[1] for g in graphs), 3)
    torch.testing.assert_close(e.mean(0), torch.zeros(3), atol=1e-5, rtol=0)
    torch.testing.assert_close(e.std(0), torch.ones(3), atol=1e-5, rtol=0)
    assert "edge_mean" not in gcn.GraphEncoder(small(node_layout=True)).state_dict()  # other encoders: same keys


# --- 6. the new convolution and pooling ---------------------------------------------------------------------------

def layout_graphs(spec: GCNSpec, flip_up: bool = False):
    """Five small graphs (one without edges, one empty); `flip_up` mirrors every scene top to bottom (the same
    lengths and image columns, the rises and rows negated)."""
    rng = np.random.default_rng(0)
    graphs = []
    for k in range(5):
        n = [4, 3, 5, 3, 0][k]
        ruf = rng.normal(size=(n, 3)) + np.array([0.0, 0.0, 3.0])
        if flip_up:
            ruf = ruf * np.array([1.0, -1.0, 1.0])
        x = np.column_stack([rng.integers(1, 40, n), rng.random((n, 3))]).astype(np.float32)
        cached = complete_graph(x, TO_FRAME["monograph"](ruf), f"ai_001_00{k % 2 + 1}", f"f{k}")
        graphs.append(gcn.encoder_graph(cached, 0.0 if k == 3 else math.inf, spec, "monograph"))
    return graphs


@pytest.mark.parametrize("choice, width", [
    (dict(conv="transformer"), 8),
    (dict(conv="transformer", edge_layout=True, node_layout=True, linear=False), 8),
    (dict(pooling="attention"), 16),
    (dict(conv="gine", edge_layout=True), 8),
    (dict(conv="gatv2", edge_layout=True, pair_readout=True), 24),
])
def test_new_layers_run_forward_and_backward(choice, width):
    torch.manual_seed(0)
    spec = small(**choice)
    model = gcn.GraphEncoder(spec)
    graphs = layout_graphs(spec)
    model.set_colour_stats(graphs)
    if spec.conv == "transformer":
        assert [type(c).__name__ for c in model.convs] == ["TransformerConv"] * 2
        assert model.convs[0].heads == 4 and model.convs[0].out_channels == 4   # hidden 16 over 4 heads
    z = model(gcn.GraphPool(graphs).batch(range(len(graphs))))
    assert z.shape == (5, width) == (5, model.out_channels) and torch.isfinite(z).all()
    (z ** 2).sum().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


@pytest.mark.parametrize("choice, reads_up", [
    (dict(conv="gine"), False), (dict(conv="gine", edge_layout=True), True),
    (dict(conv="transformer"), False), (dict(conv="transformer", edge_layout=True), True),
    (dict(), False), (dict(node_layout=True), True),
])
def test_the_layout_reaches_the_embedding(choice, reads_up):
    """Mirroring the scenes top to bottom keeps every length: an encoder reading lengths only does not see it, one
    reading the layout (edge rises and angles, node rows) does."""
    model, = twins(a=choice)
    z, flipped = (gcn.embed(model, layout_graphs(model.spec, flip)) for flip in (False, True))
    assert torch.allclose(z, flipped, atol=1e-6) != reads_up


# --- 7. training with family mining -------------------------------------------------------------------------------

def family_graphs(per: int = 10, seed: int = 0):
    """4 settings in 2 families; siblings hold the same objects (labels, colours) in another layout."""
    rng = np.random.default_rng(seed)
    graphs = []
    for s, name in enumerate(["ai_001_001", "ai_001_002", "ai_002_001", "ai_002_002"]):
        f = s // 2
        labels = np.array([1, 2, 5 + 3 * f, 6 + 3 * f])
        layout = np.random.default_rng(100 + s).normal(size=(4, 3)) + np.array([0.0, 0.0, 3.0])
        for i in range(per):
            colour = np.full((4, 3), 0.2 + 0.5 * f) + rng.normal(0, 0.02, (4, 3))
            x = np.column_stack([labels, colour]).astype(np.float32)
            ruf = layout + rng.normal(0, 0.05, (4, 3))
            graphs.append(complete_graph(x, TO_FRAME["monograph"](ruf), name, f"{name}/cam_00/{i:04d}"))
    return graphs


def split(spec: GCNSpec):
    graphs = [gcn.encoder_graph(g, 2.0, spec, "monograph") for g in family_graphs()]
    train = [g for i, g in enumerate(graphs) if i % 10 < 8]
    val = [g for i, g in enumerate(graphs) if i % 10 >= 8]
    return train, val


@pytest.mark.parametrize("mining, other, choice", [
    ("family", "random", dict(family_share=1.0)),
    ("batch_hard_family", "batch_hard", dict(pair_readout=True, message_passing=False, edge_layout=True,
                                             node_layout=True, label_encoding="embedding", pooling="meanmax")),
])
def test_family_mining_trains_deterministically(mining, other, choice):
    spec = small(mining=mining, **choice)
    train, val = split(spec)
    assert len(train) == 32 and len(val) == 8
    r1 = gcn.train(train, val, spec, seed=0, threads=1)
    r2 = gcn.train(train, val, spec, seed=0, threads=1)
    assert len(r1.history) == 2 and all(np.isfinite(h["train_loss"]) for h in r1.history)
    s1, s2 = r1.model.state_dict(), r2.model.state_dict()
    assert s1.keys() == s2.keys() and all(torch.equal(s1[k], s2[k]) for k in s1)
    torch.manual_seed(0)                                        # train's model before its first step
    initial = gcn.GraphEncoder(spec).state_dict()
    changed = [k for k, _ in r1.model.named_parameters() if not torch.equal(s1[k], initial[k])]
    assert changed == [k for k, _ in r1.model.named_parameters()]
    r3 = gcn.train(train, val, dataclasses.replace(spec, mining=other), seed=0, threads=1)
    assert not all(torch.equal(s1[k], r3.model.state_dict()[k]) for k in s1)


def test_family_mining_draws_from_the_family_helpers(monkeypatch):
    """`mining: family` hands every epoch's negatives to `family_negatives` with the study's share;
    `batch_hard_family` takes its batches from `family_batches`."""
    calls = []
    real_negatives, real_batches = gcn.family_negatives, gcn.family_batches

    def negatives(settings, negative, share, rng):
        out = real_negatives(settings, negative, share, rng)
        calls.append(("negatives", share, bool((settings[out] != settings).all()),
                      bool(all(family(a) == family(b) for a, b in zip(settings, settings[out])))))
        return out

    def batches(settings, batch_size, rng, per_setting=4):
        calls.append(("batches", batch_size))
        return real_batches(settings, batch_size, rng, per_setting)

    monkeypatch.setattr(gcn, "family_negatives", negatives)
    monkeypatch.setattr(gcn, "family_batches", batches)
    spec = small(mining="family", family_share=1.0)
    gcn.train(*split(spec), spec, seed=0, threads=1)
    assert calls == [("negatives", 1.0, True, True)] * 2
    calls.clear()
    spec = small(mining="batch_hard_family")
    gcn.train(*split(spec), spec, seed=0, threads=1)
    assert calls == [("batches", 16)] * 2
    calls.clear()
    gcn.train(*split(SMALL), SMALL, seed=0, threads=1)
    assert calls == []


# --- 8. the study keys --------------------------------------------------------------------------------------------

def study_file(tmp_path, variant: dict, name: str = "study.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump({"name": "layout_test", "extends": "smoke", "variants": {"x": {"gcn": variant}}}))
    return p


def test_the_layout_options_load(tmp_path):
    choice = dict(conv="transformer", hidden=32, pooling="attention", mining="batch_hard_family",
                  family_share=0.25, node_layout=True, edge_layout=True, pair_readout=True, message_passing=False)
    s = load_study(study_file(tmp_path, choice))
    spec = s.gcn_spec("x")
    assert {k: getattr(spec, k) for k in choice} == choice
    assert s.gcn_spec("gcn").family_share == 0.5 and not s.gcn_spec("gcn").pair_readout


@pytest.mark.parametrize("variant, key", [
    (dict(family_share=1.5), r"variants\.x\.gcn\.family_share: expected a share in \[0, 1\], got 1.5"),
    (dict(family_share=-0.1), r"variants\.x\.gcn\.family_share"),
    (dict(mining="nope"), r"variants\.x\.gcn\.mining: expected one of random, batch_hard, family, batch_hard_family"),
    (dict(pooling="sum"), r"variants\.x\.gcn\.pooling: expected one of max, meanmax, attention"),
    (dict(conv="transformer", hidden=30), r"variants\.x\.gcn\.hidden: conv: transformer needs hidden divisible"),
    (dict(node_layout="yes"), r"variants\.x\.gcn\.node_layout"),
])
def test_bad_layout_options_name_the_key(tmp_path, variant, key):
    with pytest.raises(StudyError, match=key):
        load_study(study_file(tmp_path, variant))


def published_copy(tmp_path, change):
    data = yaml.safe_load((paths.PARAMS / "published.yaml").read_text())
    (tmp_path / "graphs").mkdir(exist_ok=True)
    data["graphs_root"] = str(tmp_path / "graphs")
    change(data)
    p = tmp_path / "published.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_the_published_study_refuses_the_layout_of_positions(tmp_path):
    """The published study (graphs_root) loads with its own `layout` variant (pair readout over lengths), and
    refuses node_layout and edge_layout wherever they are asked."""
    s = load_study(published_copy(tmp_path, lambda d: None))
    assert s.gcn_spec("layout").pair_readout and not s.gcn_spec("layout").edge_layout
    for where, change in [
        ("variants.layout.gcn.node_layout", lambda d: d["variants"]["layout"]["gcn"].update(node_layout=True)),
        ("variants.layout.gcn.edge_layout", lambda d: d["variants"]["layout"]["gcn"].update(edge_layout=True)),
        ("gcn.edge_layout", lambda d: d["gcn"].update(edge_layout=True)),
        ("gcn.node_layout", lambda d: d["gcn"].update(node_layout=True)),
    ]:
        key = where.replace(".", "[.]")
        with pytest.raises(StudyError, match=rf"published[.]yaml: {key}: published graphs hold no node positions"):
            load_study(published_copy(tmp_path, change))
