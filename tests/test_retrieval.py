"""The protocol and the metrics on hand-built embeddings with known answers."""
import numpy as np
import pytest

from monolib.data.protocols import ProtocolDataError, family, protocol_settings
from monolib.params import Protocol
from monolib.retrieval.evaluate import draw_protocol, evaluate, evaluate_protocols, protocol_seed
from monolib.retrieval.metrics import metrics_from_hits


def test_metrics_from_known_hits():
    hits = np.array([[1, 0, 0, 0], [0, 1, 1, 0], [0, 0, 0, 0]], bool)
    m = metrics_from_hits(hits, [1, 2], [2, 4])
    assert m["recall@1"] == pytest.approx(100 / 3)
    assert m["recall@2"] == pytest.approx(200 / 3)
    assert m["precision@2"] == pytest.approx(100 * (0.5 + 0.5 + 0) / 3)
    assert m["precision@4"] == pytest.approx(100 * (0.25 + 0.5 + 0) / 3)


def test_protocol_never_retrieves_own_queries_and_draw_is_seeded():
    pr = Protocol(settings=3, frames=5, queries=3, positives=2, recall_k=[1], precision_k=[2])
    settings = np.repeat(["a", "b", "c"], 5)
    frames = [f"{s}/cam_00/{i:04d}" for i, s in enumerate(settings)]
    # all frames of a setting share one point, so a query's nearest frames are its own setting's frames
    emb = np.repeat(np.eye(3), 5, axis=0).astype(np.float32)
    m, rankings, draw = evaluate(emb, frames, settings, pr, seed=3)
    assert draw.is_query.sum() == 9 and (~draw.is_query).sum() == 6
    queries = set(np.asarray(frames)[draw.is_query])
    same = rankings.query_setting == rankings.match_setting
    assert not (rankings[same].match.isin(queries)).any()
    assert (rankings.query != rankings.match).all()
    assert m["recall@1"] == 100.0 and m["precision@2"] == 100.0
    assert (draw_protocol(frames, settings, pr, 3).is_query == draw.is_query).all()
    assert not (draw_protocol(frames, settings, pr, 4).is_query == draw.is_query).all()


def test_known_ranking_gives_known_recall():
    """Two settings A, B of 4 frames (2 queries, 2 positives) on a line, placed so that every ranking is known:

        position  0    1    9    12   20   30   40   41.5
        frame     qa1  pa1  qb1  pb1  qa2  pa2  qb2  pb2     (q: query, p: positive; a/b: setting A/B)

    A query's candidates are its own positives and every frame of the other setting (never its own setting's
    queries: qa1 does not see qa2 at distance 20), so the rankings and their hits (own setting = 1) are
        qa1: pa1 1, qb1 9, pb1 12, pa2 30, qb2 40, pb2 41.5        -> 1 0 0 1 0 0
        qa2: pb1 8, pa2 10, qb1 11, pa1 19, qb2 20, pb2 21.5       -> 0 1 0 1 0 0
        qb1: pb1 3, pa1 8, qa1 9, qa2 11, pa2 21, pb2 32.5         -> 1 0 0 0 0 1
        qb2: pb2 1.5, pa2 10, qa2 20, pb1 28, pa1 39, qa1 40       -> 1 0 0 1 0 0
    recall@1 = 3/4, recall@2 = 4/4, precision@2 = (1/2 + 1/2 + 1/2 + 1/2) / 4, precision@4 = (2 + 2 + 1 + 2) / 16."""
    pr = Protocol(settings=2, frames=4, queries=2, positives=2, recall_k=[1, 2], precision_k=[2, 4])
    settings = np.array(["ai_001_001"] * 4 + ["ai_002_001"] * 4)
    frames = [f"{s}/cam_00/{i:04d}" for i, s in enumerate(settings)]
    seed = 5
    draw = draw_protocol(frames, settings, pr, seed)  # the roles `evaluate` will draw with the same seed
    place = {"ai_001_001": ([0.0, 20.0], [1.0, 30.0]), "ai_002_001": ([9.0, 40.0], [12.0, 41.5])}
    emb = np.zeros((8, 1), np.float32)
    name = {}
    for s, (queries, positives) in place.items():
        idx = np.flatnonzero(settings == s)
        for i, x, n in zip(idx[draw.is_query[idx]], queries, ("q1", "q2")):
            emb[i], name[frames[i]] = x, s[3:6] + n
        for i, x, n in zip(idx[~draw.is_query[idx]], positives, ("p1", "p2")):
            emb[i], name[frames[i]] = x, s[3:6] + n
    metrics, rankings, again = evaluate(emb, frames, settings, pr, seed)
    assert (again.is_query == draw.is_query).all()
    assert metrics == pytest.approx({"recall@1": 75.0, "recall@2": 100.0, "precision@2": 50.0,
                                     "precision@4": 100 * 7 / 16})
    got = {name[q]: [(name[m], d) for m, d in zip(r.match, r.distance)] for q, r in rankings.groupby("query")}
    assert got == {
        "001q1": [("001p1", 1), ("002q1", 9), ("002p1", 12), ("001p2", 30), ("002q2", 40), ("002p2", 41.5)],
        "001q2": [("002p1", 8), ("001p2", 10), ("002q1", 11), ("001p1", 19), ("002q2", 20), ("002p2", 21.5)],
        "002q1": [("002p1", 3), ("001p1", 8), ("001q1", 9), ("001q2", 11), ("001p2", 21), ("002p2", 32.5)],
        "002q2": [("002p2", 1.5), ("001p2", 10), ("001q2", 20), ("002p1", 28), ("001p1", 39), ("001q1", 40)],
    }
    assert (rankings.groupby("query")["rank"].apply(list) == [[1, 2, 3, 4, 5, 6]] * 4).all()
    # the same hits through the metric function alone
    hits = np.array([[1, 0, 0, 1, 0, 0], [0, 1, 0, 1, 0, 0], [1, 0, 0, 0, 0, 1], [1, 0, 0, 1, 0, 0]], bool)
    assert metrics_from_hits(hits, [1, 2], [2, 4]) == pytest.approx(metrics)


def test_protocol_checks_frame_counts():
    pr = Protocol(settings=2, frames=3, queries=2, positives=1)
    with pytest.raises(ValueError, match="frames"):
        draw_protocol(["x"] * 5, np.array(["a", "a", "a", "b", "b"]), pr, 0)


# ---- two protocols: paper (different families) and siblings (pairs of one family) ----------------------------------

# the lead's generator: families ai_9FF with one test setting each, the first ones with a sibling _002
NEW = ["ai_900_001", "ai_900_002", "ai_901_001", "ai_901_002", "ai_902_001", "ai_903_001"]
# the former generator: families of 2 (a study of 2 paper settings and 2 sibling families fits it too)
OLD = ["ai_900_001", "ai_900_002", "ai_901_001", "ai_901_002"]


def test_family_is_the_volume():
    assert family("ai_001_002") == "ai_001" and family("ai_915_001") == "ai_915"


@pytest.mark.parametrize("names, settings, siblings, paper, pairs", [
    (NEW, 4, 2, ["ai_900_001", "ai_901_001", "ai_902_001", "ai_903_001"],
     ["ai_900_001", "ai_900_002", "ai_901_001", "ai_901_002"]),
    (NEW, 3, 1, ["ai_900_001", "ai_901_001", "ai_902_001"], ["ai_900_001", "ai_900_002"]),
    (OLD, 2, 2, ["ai_900_001", "ai_901_001"], OLD),
    (NEW, 4, 0, ["ai_900_001", "ai_901_001", "ai_902_001", "ai_903_001"], None),
])
def test_protocol_settings_paper_families_differ_and_siblings_are_pairs(names, settings, siblings, paper, pairs):
    pr = Protocol(settings=settings, siblings=siblings)
    chosen = protocol_settings(names[::-1], pr)  # order of the input does not matter
    assert chosen["paper"] == paper
    assert len({family(s) for s in chosen["paper"]}) == settings            # every paper setting: another family
    if pairs is None:
        assert list(chosen) == ["paper"]
    else:
        assert chosen["siblings"] == pairs
        fams = [family(s) for s in chosen["siblings"]]
        assert len(set(fams)) == siblings and all(fams.count(f) == 2 for f in fams)   # pairs of one family
    # the rule applied to the union of its own choice (what a cell's test frames hold) gives the same choice
    union = sorted(set().union(*chosen.values()))
    assert protocol_settings(union, pr) == chosen


@pytest.mark.parametrize("settings, siblings", [(3, 0), (4, 0), (7, 0), (9, 0), (5, 2), (4, 1)])
def test_protocol_settings_in_turn_from_each_family_on_real_data(settings, siblings):
    """`families: false` (real Hypersim, published graphs): the first setting of each family, then the second of
    each, ... so that no family holds two settings more than another; where there are as many families as
    settings, the same choice as the rule of different families; and the rule applied to the union of its own
    choice gives that choice again."""
    names = [f"ai_{v}_{n:03d}" for v, count in (("024", 4), ("026", 3), ("027", 2)) for n in range(1, count + 1)]
    pr = Protocol(settings=settings, siblings=siblings, families=False)
    chosen = protocol_settings(names[::-1], pr)
    counts = [sum(family(c) == f for c in chosen["paper"]) for f in ("ai_024", "ai_026", "ai_027")]
    assert len(chosen["paper"]) == settings and max(counts) - min(counts) <= 1 or counts[2] == 2, counts
    assert all(f"ai_{v}_001" in chosen["paper"] for v in ("024", "026", "027"))
    if settings == 3:
        assert chosen == protocol_settings(names, Protocol(settings=3, siblings=siblings, families=True))
    union = sorted(set().union(*chosen.values()))
    assert protocol_settings(union, pr) == chosen
    with pytest.raises(ProtocolDataError, match=r"paper protocol needs 10 test settings.*found 9"):
        protocol_settings(names, Protocol(settings=10, families=False))


def test_protocol_settings_name_what_is_missing():
    with pytest.raises(ProtocolDataError, match=r"paper protocol needs 5 test settings of different families.*"
                                                r"protocol.settings.*found 4 families"):
        protocol_settings(NEW, Protocol(settings=5))
    with pytest.raises(ProtocolDataError, match=r"siblings protocol needs 3 families.*protocol.siblings.*found 2 "
                                                r"\(ai_900, ai_901\); families without a sibling: ai_902, ai_903"):
        protocol_settings(NEW, Protocol(settings=4, siblings=3))


def cell_frames(names, per: int):
    settings = np.repeat(names, per)
    frames = [f"{s}/cam_00/{i % per:04d}" for i, s in enumerate(settings)]
    return frames, settings


def test_candidates_per_protocol():
    """Each query's candidates: its own setting's positives and every frame of its protocol's other settings (in
    `siblings`, its sibling's included; never a setting of the other protocol alone)."""
    names = ["ai_001_001", "ai_001_002", "ai_002_001", "ai_003_001"]
    pr = Protocol(settings=3, siblings=1, frames=4, queries=2, positives=2, recall_k=[1], precision_k=[2])
    frames, settings = cell_frames(names, 4)
    rng = np.random.default_rng(0)
    emb = rng.normal(size=(len(frames), 8)).astype(np.float32)
    out = evaluate_protocols(emb, frames, settings, pr, seed=5)
    assert list(out) == ["paper", "siblings"]
    assert out["paper"].settings == ["ai_001_001", "ai_002_001", "ai_003_001"]
    assert out["siblings"].settings == ["ai_001_001", "ai_001_002"]
    for name, r in out.items():
        table = r.protocol_table()
        assert set(table["protocol"]) == {name} and set(r.rankings["protocol"]) == {name}
        assert sorted(table["setting"].unique()) == r.settings and len(table) == 4 * len(r.settings)
        role = table.set_index("frame")["role"]
        # 10 candidates in paper (2 + 2 x 4), 6 in siblings (2 + 4): the top 10 lists every one of them
        for q, g in r.rankings.groupby("query"):
            own = q.split("/")[0]
            expected = {f for f in table["frame"] if (f.split("/")[0] != own) or role[f] == "positive"}
            assert set(g["match"]) == expected, (name, q)
        assert r.metrics == pytest.approx(metrics_from_hits(
            (r.rankings.match_setting == r.rankings.query_setting).to_numpy().reshape(
                len(set(r.rankings["query"])), -1),
            [1], [2]))
    # the draws are seeded per protocol: the same cell seed gives the same draws, another protocol another seed
    again = evaluate_protocols(emb, frames, settings, pr, seed=5)
    for name in out:
        assert (again[name].draw.is_query == out[name].draw.is_query).all()
        assert out[name].seed == protocol_seed(5, name)
    assert protocol_seed(5, "paper") != protocol_seed(5, "siblings") != protocol_seed(6, "siblings")


def test_a_sibling_that_looks_alike_fools_only_the_siblings_protocol():
    """ai_001_001's queries at 0, its positives at 1 (the siblings draw), its sibling ai_001_002 at 0.5, another
    family at 100: in `paper` (no ai_001_002) the queries of ai_001_001 find their own setting; in `siblings` they
    find the sibling first."""
    names = ["ai_001_001", "ai_001_002", "ai_002_001"]
    pr = Protocol(settings=2, siblings=1, frames=4, queries=2, positives=2, recall_k=[1], precision_k=[2])
    frames, settings = cell_frames(names, 4)
    emb = np.zeros((len(frames), 1), np.float32)
    sib = evaluate_protocols(emb, frames, settings, pr, seed=0)["siblings"].protocol_table().set_index("frame")
    for i, f in enumerate(frames):
        if settings[i] == "ai_001_001":
            emb[i] = 1.0 if sib.loc[f, "role"] == "positive" else 0.0
        else:
            emb[i] = 0.5 if settings[i] == "ai_001_002" else 100.0
    out = evaluate_protocols(emb, frames, settings, pr, seed=0)
    top1 = {n: r.rankings[(r.rankings["rank"] == 1) & (r.rankings.query_setting == "ai_001_001")]
            for n, r in out.items()}
    assert len(top1["paper"]) == len(top1["siblings"]) == 2
    assert (top1["paper"].match_setting == "ai_001_001").all()
    assert (top1["siblings"].match_setting == "ai_001_002").all()
    assert out["paper"].metrics["recall@1"] > out["siblings"].metrics["recall@1"]


def test_a_cell_without_the_frames_of_a_protocol_is_one_clear_error():
    names = ["ai_001_001", "ai_001_002", "ai_002_001"]
    frames, settings = cell_frames(names, 4)
    emb = np.zeros((len(frames), 2), np.float32)
    with pytest.raises(ProtocolDataError, match="families without a sibling: ai_002"):
        evaluate_protocols(emb, frames, settings, Protocol(settings=2, siblings=2, frames=4, queries=2, positives=2), 0)
    with pytest.raises(ProtocolDataError, match="has 4 frames, 5 expected"):
        evaluate_protocols(emb, frames, settings, Protocol(settings=2, siblings=1, frames=5, queries=3, positives=2), 0)


def test_select_frames_takes_the_union_of_the_protocols(tmp_path):
    """Test frames: the paper settings (one per family, the first with enough frames) and both settings of the
    sibling families, `protocol.frames` each; a setting with too few frames is not eligible."""
    from hypersim_files import write_setting

    from monolib.data.selection import select_frames
    from monolib.data.dataset import open_dataset
    from monolib.params import load_study

    frames = {"ai_001_001": 3, "ai_001_002": 3, "ai_002_001": 3, "ai_003_001": 2, "ai_003_002": 3, "ai_004_001": 3}
    for name, n in frames.items():
        write_setting(tmp_path, name, frames=n, split="test", height=12, width=16)
    for i in range(3):
        write_setting(tmp_path, f"ai_05{i}_001", frames=2, split="train", height=12, width=16)
    s = load_study("smoke")
    s.dataset.source, s.dataset.root = "hypersim", str(tmp_path)
    s.protocol = Protocol(settings=4, siblings=1, frames=3, queries=2, positives=1)
    ds = open_dataset(s)
    sel = select_frames(s, ds, 1)
    by = {}
    for f in sel.test:
        by.setdefault(f.setting, []).append(f.key)
    assert sorted(by) == ["ai_001_001", "ai_001_002", "ai_002_001", "ai_003_002", "ai_004_001"]
    assert all(len(v) == 3 for v in by.values())
    assert [f.setting for f in sel.val] == ["ai_052_001"] * 2
    chosen = protocol_settings([f.setting for f in sel.test], s.protocol)
    assert chosen["paper"] == ["ai_001_001", "ai_002_001", "ai_003_002", "ai_004_001"]
    assert chosen["siblings"] == ["ai_001_001", "ai_001_002"]
    s.protocol = Protocol(settings=4, siblings=2, frames=3, queries=2, positives=1)
    with pytest.raises(ProtocolDataError, match=r"with fewer than 3 frames: ai_003_001 \(2\)\).*found 1 \(ai_001\); "
                                                r"families without a sibling: ai_002, ai_003, ai_004"):
        select_frames(s, ds, 1)
    s.protocol = Protocol(settings=5, siblings=0, frames=3, queries=2, positives=1)
    with pytest.raises(ProtocolDataError, match="needs 5 test settings of different families.*found 4 families"):
        select_frames(s, ds, 1)
