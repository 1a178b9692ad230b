"""The protocol and the metrics on hand-built embeddings with known answers."""
import numpy as np
import pytest

from monolib.params import Protocol
from monolib.retrieval import draw_protocol, evaluate, metrics_from_hits, rank


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
    pr = Protocol(settings=2, frames=3, queries=2, positives=1, recall_k=[1, 2], precision_k=[2])
    settings = np.array(["a", "a", "a", "b", "b", "b"])
    frames = [f"f{i}" for i in range(6)]
    draw = draw_protocol(frames, settings, pr, 0)
    emb = np.zeros((6, 1), np.float32)
    emb[:, 0] = [0, 10, 20, 30, 40, 50]
    # put setting a's positive far away: its queries then find setting b first
    pos_a = np.flatnonzero((settings == "a") & ~draw.is_query)[0]
    emb[pos_a] = 1000
    q, idx, dist = rank(emb, draw, k=4)
    hits = settings[idx] == settings[q][:, None]
    assert not hits[settings[q] == "a", 0].any()
    assert (np.diff(dist, axis=1) >= 0).all()


def test_protocol_checks_frame_counts():
    pr = Protocol(settings=2, frames=3, queries=2, positives=1)
    with pytest.raises(ValueError, match="frames"):
        draw_protocol(["x"] * 5, np.array(["a", "a", "a", "b", "b"]), pr, 0)
