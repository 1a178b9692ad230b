"""Scene graphs from hand-built geometry: known medians, known edges at a threshold, empty and one-node frames."""
import math

import numpy as np
import pytest

from monolib.data.hypersim import Camera
from monolib.graphs.build import (
    at_threshold, build_scene_graph, complete_graph, grouped_median, grouped_median_u8, scene_nodes
)

CAM = Camera.canonical(8, 6)


def frame_with_blocks():
    """8x6 frame: label 5 on the left 4 columns at 2 m, label 7 on the right 4 at 5 m; one NaN, one -1 pixel."""
    depth = np.full((6, 8), 2.0, np.float32)
    depth[:, 4:] = 5.0
    semantic = np.full((6, 8), 5, np.int16)
    semantic[:, 4:] = 7
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[:, :4] = (255, 0, 0)
    rgb[:, 4:] = (0, 0, 255)
    depth[0, 0] = np.nan          # left out
    semantic[5, 7] = -1            # left out
    return rgb, depth, semantic


def test_nodes_are_per_axis_medians_of_back_projected_points():
    rgb, depth, semantic = frame_with_blocks()
    x, pos = scene_nodes(rgb, depth, semantic, CAM)
    assert x[:, 0].tolist() == [5.0, 7.0]
    np.testing.assert_allclose(x[:, 1:], [[1, 0, 0], [0, 0, 1]])
    pts = CAM.backproject(depth)
    for row, label in enumerate([5, 7]):
        keep = (semantic == label) & np.isfinite(depth)
        np.testing.assert_allclose(pos[row], np.median(pts[keep], axis=0), rtol=1e-6)
    assert pos[0, 2] == pytest.approx(-2.0) and pos[1, 2] == pytest.approx(-5.0)  # camera looks along -z


def test_edges_at_a_threshold_both_directions_with_lengths():
    rgb, depth, semantic = frame_with_blocks()
    _, pos = scene_nodes(rgb, depth, semantic, CAM)
    length = float(np.linalg.norm(pos[0] - pos[1]))
    g = build_scene_graph(rgb, depth, semantic, CAM, threshold=length + 0.01)
    assert g.edge_index.tolist() == [[0, 1], [1, 0]]
    np.testing.assert_allclose(g.edge_attr.squeeze(1).numpy(), [length, length], rtol=1e-5)
    assert build_scene_graph(rgb, depth, semantic, CAM, threshold=length - 0.01).edge_index.shape == (2, 0)
    assert build_scene_graph(rgb, depth, semantic, CAM, threshold=math.inf).edge_index.shape == (2, 2)


def test_complete_graph_then_threshold_equals_direct_build():
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 9, (24, 32)).astype(np.float32)
    semantic = rng.integers(1, 12, (24, 32)).astype(np.int16) * (rng.random((24, 32)) > 0.3) - 0
    semantic[semantic == 0] = -1
    rgb = rng.integers(0, 255, (24, 32, 3), dtype=np.uint8)
    cam = Camera.canonical(32, 24)
    x, pos = scene_nodes(rgb, depth, semantic, cam)
    full = complete_graph(x, pos, "ai_900_001", "ai_900_001/cam_00/0000")
    for t in (0.3, 1.0, 2.0, math.inf):
        direct = build_scene_graph(rgb, depth, semantic, cam, t)
        via = at_threshold(full, t)

        def as_set(ei):
            return set(map(tuple, ei.t().tolist()))

        assert as_set(direct.edge_index) == as_set(via.edge_index)
        assert via.edge_index.shape[1] % 2 == 0


def test_empty_and_one_node_frames():
    depth = np.full((6, 8), np.nan, np.float32)
    semantic = np.full((6, 8), 3, np.int16)
    g = build_scene_graph(None, depth, semantic, CAM, 1.0)
    assert g.num_nodes == 0 and g.edge_index.shape == (2, 0)
    g = build_scene_graph(None, np.ones((6, 8), np.float32), np.full((6, 8), -1, np.int16), CAM, 1.0)
    assert g.num_nodes == 0
    g = build_scene_graph(None, np.ones((6, 8), np.float32), semantic, CAM, math.inf)
    assert g.num_nodes == 1 and g.edge_index.shape == (2, 0)
    full = complete_graph(np.zeros((0, 4)), np.zeros((0, 3)), "a", "b")
    assert at_threshold(full, 1.0).edge_index.shape == (2, 0)


def test_grouped_median_matches_numpy_on_even_and_odd_groups():
    rng = np.random.default_rng(0)
    labels = rng.integers(1, 41, 5001)
    values = rng.normal(size=(5001, 3)) * 100
    uniq, med = grouped_median(labels, values.T)
    for i, label in enumerate(uniq):
        np.testing.assert_allclose(med[i], np.median(values[labels == label], axis=0), rtol=1e-9, atol=1e-9)


def test_colour_medians_from_histograms_are_exact():
    rng = np.random.default_rng(2)
    labels = rng.integers(1, 41, 4001)
    labels[:2] = 40                      # the largest id, and a label with only one pixel
    labels[labels == 17] = 18
    labels[7] = 17
    colours = rng.integers(0, 256, (4001, 3), dtype=np.uint8)
    uniq = np.flatnonzero(np.bincount(labels))
    med = grouped_median_u8(labels, colours, uniq)
    for i, label in enumerate(uniq):
        assert med[i].tolist() == np.median(colours[labels == label], axis=0).tolist()  # even counts: mean of two


def test_all_valid_and_masked_frames_give_the_same_nodes():
    """The fast path for fully valid frames (predicted ones) and the indexed path agree; float colours work too."""
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 9, (24, 32)).astype(np.float32)
    semantic = rng.integers(1, 9, (24, 32)).astype(np.int16)
    rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    cam = Camera.canonical(32, 24)
    x, pos = scene_nodes(rgb, depth, semantic, cam)
    masked = depth.copy()
    masked[0, 0] = np.nan                 # one invalid pixel forces the indexed path
    xm, pm = scene_nodes(rgb, masked, semantic, cam)
    keep = np.isfinite(masked)
    pts = cam.backproject(depth)
    for row, label in enumerate(xm[:, 0].astype(int)):
        sel = keep & (semantic == label)
        np.testing.assert_allclose(pm[row], np.median(pts[sel], axis=0), rtol=1e-6)
        np.testing.assert_allclose(xm[row, 1:], np.median(rgb[sel], axis=0) / 255.0, rtol=1e-6)
    assert x[:, 0].tolist() == xm[:, 0].tolist()
    xf, pf = scene_nodes(rgb.astype(np.float32) / 255.0, depth, semantic, cam)
    np.testing.assert_allclose(xf, x, atol=1e-6)
    np.testing.assert_array_equal(pf, pos)


def test_mismatched_shapes_raise():
    with pytest.raises(ValueError, match="differ"):
        scene_nodes(None, np.ones((4, 4), np.float32), np.ones((4, 5), np.int16), CAM)


def test_a_frame_with_a_missing_file_becomes_an_empty_graph(tmp_path, monkeypatch):
    """Missing Hypersim files are a normal case: the graph stage logs them and goes on."""
    import yaml
    from hypersim_files import write_setting

    from monolib import paths
    from monolib.graphs import scenegraphs
    from monolib.params import load_study

    root = tmp_path / "data"
    for i, setting in enumerate(["ai_001_001", "ai_002_001", "ai_001_002", "ai_002_002", "ai_003_001", "ai_003_002"]):
        write_setting(root, setting, frames=2, split="test" if i < 2 else "train")
    (root / "ai_001_001" / "images" / "scene_cam_00_geometry_hdf5" / "frame.0001.depth_meters.hdf5").unlink()
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data.update(name="missing_files_test", scenarios={"s1": {"depth": "gt", "semantic": "gt"}})
    data["dataset"].update(source="hypersim", root=str(root), workers=1)
    data["protocol"].update(settings=2, siblings=0, frames=2, queries=1, positives=1)
    data["gcn"].update(val_settings=1)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(data))
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    graphs = scenegraphs.load(load_study(p), "s1")
    by_frame = {g.frame: g for g in graphs["test"]}
    assert by_frame["ai_001_001/cam_00/0001"].num_nodes == 0
    assert by_frame["ai_001_001/cam_00/0000"].num_nodes == 2  # wall and floor


def test_the_original_double_loop_builds_the_same_graph():
    """The benchmark's reference (`monolib.bench.frames.original_graph`, the original code's per-pixel loop) and ours
    agree node for node and edge for edge, with invalid depth and unlabelled pixels in the frame."""
    from monolib.bench.frames import original_graph
    from monolib.data.hypersim import Camera
    from monolib.graphs.build import build_scene_graph

    rng = np.random.default_rng(5)
    semantic = rng.integers(-1, 6, (24, 32)).astype(np.int16)
    depth = rng.uniform(0.5, 6.0, (24, 32)).astype(np.float32)
    depth[3:6, 4:9] = np.nan
    depth[10, :] = 0.0
    rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    cam = Camera.canonical(32, 24)
    g = build_scene_graph(rgb, depth, semantic, cam, 0.35)
    x, pos, edges = original_graph(rgb, depth, semantic, cam, 0.35)
    np.testing.assert_allclose(g.x.numpy(), x, atol=1e-6)
    np.testing.assert_allclose(g.pos.numpy(), pos, atol=1e-5)
    assert sorted(map(tuple, g.edge_index.t().tolist())) == sorted((i, j) for i, j, _ in edges)
    assert 0 < len(edges) < len(x) * (len(x) - 1)


# ---- the original code's back-projection (graphs.projection: monograph) --------------------------------------

def test_monograph_projection_of_one_hand_computed_pixel():
    """One labelled pixel (row 1, column 6) of an 8x6 frame at Euclidean distance 3 m: the original code puts it at
    x = (6 - 8 // 2) z / f_w, y = (1 - 6 // 2) z / f_h, z = 3, with f = 577.35 / 433.01 px scaled by 8 / 1024."""
    f_w, f_h = 577.3502691896258 * 8 / 1024, 433.0127018922193 * 6 / 768  # 1000 tan(fov_y / 2), f_h * 1024 / 768
    distance = np.full((6, 8), np.nan, np.float32)
    distance[1, 6] = 3.0
    semantic = np.full((6, 8), -1, np.int16)
    semantic[1, 6] = 9
    planar = CAM.planar_from_euclidean(distance)  # the graph stage's depth sources are planar
    x, pos = scene_nodes(None, planar, semantic, CAM, "monograph")
    assert x[:, 0].tolist() == [9.0]
    assert pos[0] == pytest.approx([2 * 3.0 / f_w, -2 * 3.0 / f_h, 3.0], rel=1e-6)
    # the exact camera puts the same pixel elsewhere: the pixel centre's ray, planar depth as -z
    _, exact = scene_nodes(None, planar, semantic, CAM, "exact")
    assert np.linalg.norm(exact[0]) == pytest.approx(3.0, rel=1e-6)
    assert not np.allclose(np.abs(exact[0]), np.abs(pos[0]), atol=0.05)


def test_monograph_projection_gives_the_same_nodes_at_two_resolutions():
    """A depth map and its 2x upsampling (each pixel four times) give the same nodes: z exactly, x and y within the
    quarter pixel by which the principal point (W // 2, H // 2) and the pixel grid shift at the finer size."""
    rng = np.random.default_rng(3)
    distance = np.repeat(np.repeat(rng.uniform(1.0, 12.0, (3, 4)), 4, 0), 4, 1).astype(np.float32)  # 12 x 16 blocks
    semantic = np.repeat(np.repeat(np.arange(12).reshape(3, 4) + 1, 4, 0), 4, 1).astype(np.int16)
    nodes = {}
    for scale in (1, 2):
        d = np.repeat(np.repeat(distance, scale, 0), scale, 1)
        s = np.repeat(np.repeat(semantic, scale, 0), scale, 1)
        cam = Camera.canonical(16 * scale, 12 * scale)
        nodes[scale] = scene_nodes(None, cam.planar_from_euclidean(d), s, cam, "monograph")
    (x1, p1), (x2, p2) = nodes[1], nodes[2]
    assert np.array_equal(x1, x2)
    assert p2[:, 2] == pytest.approx(p1[:, 2], rel=1e-6)
    f = np.array([577.3502691896258 * 16 / 1024, 433.0127018922193 * 12 / 768])  # f_w, f_h at the coarse size
    shift = 0.25 * p1[:, 2:] / f  # a quarter pixel at each node's depth
    assert (np.abs(p2[:, :2] - p1[:, :2]) <= shift + 1e-5).all()
    # and the lengths with them, within the two nodes' shifts: the metres do not depend on the resolution
    g1, g2 = complete_graph(x1, p1), complete_graph(x2, p2)
    i, j = g1.pair_index.numpy()
    bound = np.linalg.norm(shift, axis=1)
    assert (np.abs(g2.pair_len.numpy() - g1.pair_len.numpy()) <= bound[i] + bound[j] + 1e-5).all()


def test_exact_projection_is_unchanged_bit_for_bit():
    """The exact camera's nodes of a seeded frame (canonical camera: a diagonal M, so no fused multiply-add can move
    a bit) hash to what the code of 7dc39ec, before the projections, gave."""
    import hashlib

    rng = np.random.default_rng(25)
    h, w = 48, 64
    depth = rng.uniform(0.5, 9.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.05] = np.nan
    semantic = rng.integers(-1, 13, (h, w)).astype(np.int16)
    rgb = rng.integers(0, 256, (h, w, 3)).astype(np.uint8)
    x, pos = scene_nodes(rgb, depth, semantic, Camera.canonical(w, h), "exact")
    digest = hashlib.sha256(np.ascontiguousarray(x).tobytes() + np.ascontiguousarray(pos).tobytes()).hexdigest()
    assert digest == "dd84e1b9df932da40c0da41916e6b52c0be41ad52e90704a4404db5bf24166e8"
    assert np.array_equal(pos, scene_nodes(rgb, depth, semantic, Camera.canonical(w, h))[1])  # the default


def test_an_unknown_projection_is_refused():
    rgb, depth, semantic = frame_with_blocks()
    with pytest.raises(ValueError, match="projection: expected one of monograph, exact, got 'pinhole'"):
        scene_nodes(rgb, depth, semantic, CAM, "pinhole")


def test_a_graphs_file_is_read_once_per_version_of_it(tmp_path):
    """The graph stage's reader keeps what it read by the file's identity (the cells a warm kernel runs in a row
    read their scenario's file once) and reads a rebuilt file again."""
    from monolib.graphs import scenegraphs
    from monolib.io import save_torch

    path = tmp_path / "s1-key.pt"
    rgb, depth, semantic = frame_with_blocks()
    one = complete_graph(*scene_nodes(rgb, depth, semantic, CAM), "ai_001_001", "f")
    save_torch(path, {"graphs": {"train": [one], "val": [], "test": []}})
    first = scenegraphs._read_graphs(path)
    assert scenegraphs._read_graphs(path) is first
    save_torch(path, {"graphs": {"train": [one, one], "val": [], "test": []}})  # rebuilt (atomic rename)
    assert len(scenegraphs._read_graphs(path)["graphs"]["train"]) == 2
