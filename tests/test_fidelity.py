"""Data fidelity (monolib.graphs.fidelity): known answers on hand-built graphs, agreement with the shared reference
script, and the real published sample."""
import dataclasses
import json
import math
import random
import subprocess
import sys

import numpy as np
import pytest
import torch
from torch_geometric.data import Data

from monolib import paths
from monolib.graphs import fidelity, published
from monolib.params import load_study

SHARED = paths.ROOT.parent / "shared"
REFERENCE_SCRIPT = SHARED / "tools" / "fidelity_reference.py"
SAMPLE = SHARED / "data" / "published_graphs_sample" / "ai_001_001_00_graphs.pt"


def graph(setting: str, label_colours: list[tuple[int, tuple[float, float, float]]], frame: str = "") -> Data:
    """A ground-truth graph as the cache holds it: x = [NYU40 id, R, G, B] per node."""
    x = torch.tensor([[float(label), *colour] for label, colour in label_colours], dtype=torch.float32).reshape(-1, 4)
    return Data(x=x, setting=setting, frame=frame, num_nodes=len(x))


def two_settings() -> list[Data]:
    """Settings A (labels wall, floor, cabinet) and B (wall, floor, bed), 10 frames each. Wall log colour per channel:
    A at -1 +- 0.2, B at -3 +- 0.2 (alternating), so within sd 0.2, between sd 1.0, ratio 5. Floors: black in A
    (log floored at 1e-3), grey 0.5 in B, the same in every frame."""
    graphs = []
    for setting, centre, third, floor in (("ai_001_001", -1.0, 3, 0.0), ("ai_002_001", -3.0, 4, 0.5)):
        for i in range(10):
            wall = tuple([math.exp(centre + (0.2 if i % 2 else -0.2))] * 3)
            graphs.append(graph(setting, [(1, wall), (2, (floor,) * 3), (third, (0.5, 0.5, 0.5))], f"{setting}/{i}"))
    return graphs


def test_known_answers_on_two_settings():
    few = [graph("ai_003_001", [(5, (0.1, 0.1, 0.1))]) for _ in range(9)]  # 9 frames: a setting not used
    stats = fidelity.split_statistics(two_settings() + few)
    assert stats["settings"] == 2 and stats["graphs"] == 20
    for name in fidelity.NODE_STATS:
        assert stats[f"nodes per graph, {name}"] == 3
    assert stats["label-set Jaccard, within settings"] == 1.0
    assert stats["label-set Jaccard, across settings"] == 0.5  # {wall, floor} of {wall, floor, cabinet, bed}
    assert stats["wall colour sd, within settings"] == pytest.approx(0.2, abs=1e-6)
    assert stats["wall colour sd, between settings"] == pytest.approx(1.0, abs=1e-6)
    assert stats["wall colour ratio"] == pytest.approx(5.0, abs=1e-4)
    # floors: no spread within a setting; between: log(1e-3) (black, floored) against log(0.5)
    assert stats["floor colour sd, within settings"] == pytest.approx(0, abs=1e-6)
    assert stats["floor colour sd, between settings"] == pytest.approx((math.log(0.5) - math.log(1e-3)) / 2, abs=1e-5)
    assert stats["label frequency, wall"] == 1 and stats["label frequency, floor"] == 1
    assert stats["label frequency, cabinet"] == 0.5 and stats["label frequency, bed"] == 0.5
    assert stats["label frequency, chair"] == 0  # settings with < 10 frames do not count: chair (5) only there


def test_node_counts_and_jaccard_of_known_label_sets():
    # setting A: frames alternate {1, 2} and {1, 2, 3, 4} (Jaccard 1/2 between unlike frames); B: {5, 6} always
    graphs = []
    for s in ("ai_001_001", "ai_002_001"):
        for i in range(10):
            ids = [1, 2] if i % 2 else [1, 2, 3, 4]
            if s == "ai_002_001":
                ids = [5, 6]  # nothing in common with A
            graphs.append(graph(s, [(k, (0.5, 0.5, 0.5)) for k in ids]))
    stats = fidelity.split_statistics(graphs)
    assert stats["label-set Jaccard, across settings"] == 0
    # a pair of A is unlike with probability 5 * 5 / 45 = 5 / 9 (Jaccard 1/2), else 1; B's pairs are all 1
    expected = 0.5 * (1 - 5 / 9 * 0.5) + 0.5 * 1.0  # 0.861; 4000 draws: sd about 0.003
    assert stats["label-set Jaccard, within settings"] == pytest.approx(expected, abs=0.02)
    assert stats["nodes per graph, mean"] == pytest.approx((5 * 2 + 5 * 4 + 10 * 2) / 20)
    assert stats["nodes per graph, median"] == 2 and stats["nodes per graph, p90"] == 4


def test_repeated_labels_count_once_in_label_sets_and_node_colour_is_the_first():
    graphs = [graph("ai_001_001", [(1, (1.0, 1.0, 1.0)), (1, (0.0, 0.0, 0.0))]) for _ in range(10)]
    graphs += [graph("ai_002_001", [(1, (0.5, 0.5, 0.5))]) for _ in range(10)]
    stats = fidelity.split_statistics(graphs)
    assert stats["label-set Jaccard, across settings"] == 1.0
    assert stats["nodes per graph, mean"] == 1.5
    assert stats["wall colour sd, within settings"] == 0  # the first wall node (white) of every frame of A
    assert stats["wall colour sd, between settings"] == pytest.approx(abs(math.log(0.5)) / 2, abs=1e-6)


def test_empty_inputs_give_nan_not_a_crash(tmp_path, monkeypatch):
    stats = fidelity.split_statistics([])
    assert stats["settings"] == 0 and stats["graphs"] == 0
    assert all(math.isnan(v) for k, v in stats.items() if k not in ("settings", "graphs"))
    # graphs without nodes: 0 nodes, empty label sets count Jaccard 0, no walls -> NaN colours
    empty = [graph(s, []) for s in ("ai_001_001", "ai_002_001") for _ in range(10)]
    stats = fidelity.split_statistics(empty)
    assert stats["nodes per graph, mean"] == 0 and stats["label-set Jaccard, within settings"] == 0
    assert math.isnan(stats["wall colour sd, within settings"]) and math.isnan(stats["wall colour ratio"])
    assert stats["label frequency, wall"] == 0
    # one setting: nothing across settings to measure
    one = fidelity.split_statistics(two_settings()[:10])
    assert one["label-set Jaccard, within settings"] == 1.0
    assert math.isnan(one["label-set Jaccard, across settings"]) and math.isnan(one["wall colour sd, between settings"])
    # walls in fewer than 5 frames of every setting: no colour statistic
    sparse = [graph(s, [(1, (0.5, 0.5, 0.5))] if i < 4 else [(2, (0.5, 0.5, 0.5))])
              for s in ("ai_001_001", "ai_002_001") for i in range(10)]
    assert math.isnan(fidelity.split_statistics(sparse)["wall colour sd, within settings"])
    # and the files are still written, with NaN in the table
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    study = dataclasses.replace(load_study("smoke"), name="empty_test")
    _, md = fidelity.write(study, {"this study, train": fidelity.split_statistics([]), "this study, test": stats})
    text = md.read_text()
    assert ("NaN / NaN / NaN / NaN" in text and "0 of 24 pass" in text
            and "wall colour ratio (graph node colours) >= 2.0: NaN FAIL" in text)
    assert "pixel depth, median in [4, 5.6]: NaN FAIL" in text


def test_reference_file_is_read_and_the_tables_are_written(tmp_path, monkeypatch):
    ref = fidelity.read_reference()
    assert ref["real Hypersim, train"]["nodes per graph, mean"] == 8.2
    assert ref["real Hypersim, test"]["floor colour ratio"] == 4.3
    assert ref["real Hypersim, train"]["label frequency, wall"] == 0.91
    assert len([k for k in ref["real Hypersim, train"] if k.startswith("label frequency")]) == 20
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    study = dataclasses.replace(load_study("smoke"), name="table_test")
    stats = fidelity.split_statistics(two_settings())
    csv_path, md_path = fidelity.write(study, {"this study, train": stats, "this study, test": stats})
    assert csv_path.parent == paths.figures_dir("table_test") == tmp_path / "runs" / "table_test" / "figures"
    import csv

    rows = list(csv.DictReader(csv_path.open()))
    assert {r["source"] for r in rows} == {"this study, train", "this study, test", "real Hypersim, train",
                                          "real Hypersim, test", fidelity.DEVELOPMENT}
    value = {(r["statistic"], r["source"]): float(r["value"]) for r in rows}
    assert value[("wall colour ratio", "this study, train")] == pytest.approx(5.0, abs=1e-4)
    assert value[("nodes per graph, mean", "real Hypersim, test")] == 2.8
    md = md_path.read_text()
    assert ("| nodes per graph: mean / median / p10 / p90 | 3.0 / 3 / 3 / 3 | 3.0 / 3 / 3 / 3 | 8.2 / 9 / 3 / 12 "
            "| 2.8 / 2 / 1 / 6 | 8.5 / 9 / 4 / 13 |") in md
    assert "| wall colour sd within / between settings (ratio), node colours (hdr) | 0.20 / 1.00 (5.0) |" in md
    assert ("| wall colour sd within / between settings (ratio), the graphs' node colours (hdr) | NaN / NaN (NaN) |"
            in md)
    assert "| wall colour sd within / between settings (ratio), HDR color.hdf5 medians | NaN / NaN (NaN) |" in md
    assert ref["real Hypersim, train"]["pair length (monograph), median"] == 4.31
    assert ref["real Hypersim, test"]["edges per graph at 10 m (monograph)"] == 4.07
    assert ref["real Hypersim, train"]["pixel depth, share beyond 20 m"] == 0.059
    assert ref["real Hypersim, train"]["wall HDR colour sd, within settings"] == 0.47
    assert "| label-set Jaccard within / across settings | 1.00 / 0.50 |" in md
    assert "real Hypersim, train (169 settings)" in md and "this study, train (2 settings)" in md
    assert "Label frequency, real Hypersim, train (share of graphs): wall 0.91, floor 0.86, otherprop 0.73" in md
    assert "Label frequency, this study, train (share of graphs): wall 1.00, floor 1.00, cabinet 0.50, bed 0.50." in md
    assert ("nodes per graph mean 7-10: 3.0 FAIL" in md
            and "wall colour ratio (graph node colours) >= 2.0: 5.0 pass" in md)
    assert "floor colour ratio (graph node colours) >= 2.0:" in md and "wall in >= 30% of graphs: 1.00 pass" in md
    assert "otherprop in >= 30% of graphs: 0.00 FAIL" in md


def test_acceptance_targets_pass_when_met():
    stats = {"nodes per graph, mean": 8.0, "label-set Jaccard, within settings": 0.7,
             "label-set Jaccard, across settings": 0.3, "wall colour ratio": 2.5, "floor colour ratio": 2.0}
    stats.update({fidelity.frequency_name(n): 0.3 for n in fidelity.TARGET_FREQUENT})
    stats.update({"pixel depth, median": 4.79, "pixel depth, p90": 13.8, "pixel depth, share beyond 20 m": 0.059,
                  "pair length (monograph), median": 4.31, "pairs closer than 1 m (monograph)": 0.04,
                  "pairs closer than 2 m (monograph)": 0.142, "pairs closer than 5 m (monograph)": 0.6,
                  "pairs closer than 10 m (monograph)": 0.931, "wall HDR colour sd, within settings": 0.47,
                  "wall HDR colour ratio": 2.6, "floor HDR colour sd, within settings": 0.5,
                  "floor HDR colour ratio": 2.6,
                  fidelity.SETTING_LIGHT: 1.11})  # real Hypersim's own numbers pass
    assert all(ok for _, ok in fidelity.acceptance(stats))
    stats["label-set Jaccard, across settings"] = 0.41
    assert [ok for _, ok in fidelity.acceptance(stats)].count(False) == 1
    stats["wall HDR colour ratio"] = 10.7  # the mini-Hypersim of 7dc39ec: one wall four times too alike
    stats["pixel depth, median"] = 2.86
    assert [ok for _, ok in fidelity.acceptance(stats)].count(False) == 3
    stats[fidelity.SETTING_LIGHT] = 0.53  # the mini-Hypersim of quick: every place lit alike
    assert [ok for _, ok in fidelity.acceptance(stats)].count(False) == 4


def test_light_statistics_see_a_place_brighter_than_another():
    """Two settings whose every node is 4x brighter in one: their light levels differ by log 4, so the sd over the
    two is log(4) / 2; a lamp 3x the wall."""
    graphs = [graph(s, [(1, (c, c, c)), (35, (3 * c, 3 * c, 3 * c))]) for s, c in (("ai_001_001", 0.1),
                                                                                   ("ai_002_001", 0.4))
              for _ in range(10)]
    stats = fidelity.split_statistics(graphs)
    assert stats[fidelity.SETTING_LIGHT] == pytest.approx(math.log(4) / 2)
    assert stats["lamp brightness / the wall's"] == pytest.approx(3 * 0.25 / 0.25)
    assert math.isnan(stats["window brightness / the wall's"])


def random_split(rng: random.Random, settings: int) -> list[Data]:
    """Graphs like the generator's: settings with 3 to 30 frames (some below 10), clustered labels and colours,
    some frames without walls, some empty graphs, black colours (floored), settings interleaved."""
    graphs = []
    for s in range(settings):
        name = f"ai_{s:03d}_001"
        common = rng.sample(range(1, 41), 6)
        wall = [rng.uniform(0.05, 0.9) for _ in range(3)]
        for i in range(rng.randint(3, 30)):
            if rng.random() < 0.05:
                graphs.append(graph(name, []))
                continue
            extra = {rng.randint(1, 40) for _ in range(rng.randint(0, 4))}
            ids = sorted({k for k in common if rng.random() < 0.7} | extra)
            nodes = [(k, tuple(min(1.0, max(0.0, c + rng.gauss(0, 0.05))) if k == 1 else rng.choice([0.0, rng.random()])
                               for c in wall)) for k in ids]
            graphs.append(graph(name, nodes, f"{name}/{i}"))
    rng.shuffle(graphs)  # the order of first appearance decides the settings' order; the draws must follow it
    return graphs


@pytest.mark.skipif(not REFERENCE_SCRIPT.exists(), reason="shared/tools/fidelity_reference.py absent")
@pytest.mark.parametrize("seed", [0, 1])
def test_agrees_with_the_reference_script(tmp_path, seed):
    rng = random.Random(seed)
    graphs = {"train": random_split(rng, 25), "val": [], "test": random_split(rng, 5)}
    cache = tmp_path / "runs" / "fake" / "graphs" / "s1-x.pt"
    cache.parent.mkdir(parents=True)
    torch.save({"scenario": "s1", "graphs": graphs, "seconds": 0.0}, cache)
    # the script exits at its end: keep it running to read its full-precision values
    wrapper = ("import json, runpy, sys; sys.argv = ['fidelity_reference.py', 'fake']; sys.exit = lambda code=0: None; "
               f"g = runpy.run_path({str(REFERENCE_SCRIPT)!r}); import numpy as np; "
               "print(json.dumps({'settings': len(g['S']), 'nodes': float(g['n'].mean()), "
               "'within': float(np.mean(g['within'])), 'across': float(np.mean(g['across'])), "
               "'wall': float(g['ratios']['wall']), 'floor': float(g['ratios']['floor'])}))")
    done = subprocess.run([sys.executable, "-c", wrapper], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    printed, full = done.stdout.strip().splitlines()[-2:]
    ref = json.loads(full)
    ours = fidelity.split_statistics(graphs["train"])
    assert ours["settings"] == ref["settings"]
    assert ours["nodes per graph, mean"] == ref["nodes"]
    assert ours["label-set Jaccard, within settings"] == ref["within"]  # the same draws, so exactly equal
    assert ours["label-set Jaccard, across settings"] == ref["across"]
    assert ours["wall colour ratio"] == ref["wall"]
    assert ours["floor colour ratio"] == ref["floor"]
    # and the script's own printed line, at its precision
    assert printed.startswith(f"{ours['settings']:.0f} settings: ")
    assert f"nodes/graph {ours['nodes per graph, mean']:.1f}" in printed
    assert f"within {ours['label-set Jaccard, within settings']:.2f}" in printed
    assert f"across {ours['label-set Jaccard, across settings']:.2f}" in printed
    assert f"wall {ours['wall colour ratio']:.1f} floor {ours['floor colour ratio']:.1f}" in printed


@pytest.mark.skipif(not SAMPLE.exists(), reason="shared published graph sample absent")
def test_the_real_published_sample():
    graphs = [g for p in sorted(SAMPLE.parent.glob("ai_*_graphs.pt")) for g in published.read_file(p)]
    stats = fidelity.split_statistics(graphs)
    assert stats["settings"] >= 1 and stats["graphs"] == len(graphs)
    for name in ("nodes per graph, mean", "nodes per graph, median", "label-set Jaccard, within settings",
                 "wall colour sd, within settings", "floor colour sd, within settings", "label frequency, wall"):
        assert np.isfinite(stats[name]), name
    assert 1 <= stats["nodes per graph, mean"] <= 40 and 0 < stats["label-set Jaccard, within settings"] <= 1
    # the sample is one setting; as two pseudo-settings (even / odd frames) the across-setting statistics exist too
    for i, g in enumerate(graphs):
        g.setting = f"{g.setting}_{i % 2}"
    halves = fidelity.split_statistics(graphs)
    assert halves["settings"] == 2
    for name in ("label-set Jaccard, across settings", "wall colour sd, between settings", "wall colour ratio",
                 "floor colour ratio"):
        assert np.isfinite(halves[name]), name
    assert halves["wall colour ratio"] < 1  # two halves of one place: no more different than frames of it


# ---- geometry and light (the doc's "Geometry" and "Light"), like with like -------------------------------------

def pair_graph(setting: str, lengths: list[float], frame: str = "") -> Data:
    """A graph as the cache holds it, with its pairs' lengths (positions are not read)."""
    n = 1
    while n * (n - 1) // 2 < len(lengths):
        n += 1
    i, j = torch.triu_indices(n, n, offset=1)[:, : len(lengths)]
    return Data(x=torch.zeros(n, 4), pair_index=torch.stack([i, j]), pair_len=torch.tensor(lengths),
                setting=setting, frame=frame, num_nodes=n)


def test_pair_statistics_known_answers():
    """Frames with pairs 0.5, 1.5, 3, 7, 12 m, and two with no node pair (a one-node and an empty graph)."""
    graphs = [pair_graph("ai_001_001", [0.5, 1.5, 3.0, 7.0, 12.0], f"a/{i}") for i in range(10)]
    graphs += [pair_graph("ai_002_001", [], f"b/{i}") for i in range(2)]
    st = fidelity.pair_statistics(graphs, "monograph")
    assert st["pairs per graph (monograph)"] == 50 / 12
    assert st["pair length (monograph), p10"] == 0.5 and st["pair length (monograph), p90"] == 12.0
    assert st["pair length (monograph), median"] == 3.0
    assert st["pair length (monograph), mean"] == pytest.approx(4.8)
    for t, share, edges in ((1, 0.2, 10 / 12), (2, 0.4, 20 / 12), (5, 0.6, 30 / 12), (10, 0.8, 40 / 12)):
        assert st[f"pairs closer than {t} m (monograph)"] == pytest.approx(share)
        assert st[f"edges per graph at {t} m (monograph)"] == edges  # a pair counted once
    empty = fidelity.pair_statistics([pair_graph("ai_001_001", [], f"a/{i}") for i in range(10)], "exact")
    assert empty["pairs per graph (exact)"] == 0.0 and math.isnan(empty["pair length (exact), median"])


def test_depth_statistics_known_answers():
    st = fidelity.depth_statistics(np.arange(1, 101, dtype=np.float32))
    assert st["pixel depth, median"] == 50.5
    assert st["pixel depth, p10"] == pytest.approx(10.9) and st["pixel depth, p90"] == pytest.approx(90.1)
    assert st["pixel depth, share beyond 20 m"] == 0.8
    assert math.isnan(fidelity.depth_statistics(np.zeros(0))["pixel depth, median"])


def light_dataset(root, frames: int = 20):
    """Two training settings of `frames` frames (a wall 4 m ahead over a floor, canonical camera) whose files hold
    known answers: depth 3 m but for the top quarter of rows at 25 m; HDR wall colour exp(c +- 0.2) (c = -1 in the
    first setting, -3 in the second, alternating every second frame, so that every 2nd frame alternates too), floor
    exp(-2 +- 0.1) and exp(-2.5 +- 0.1)."""
    from hypersim_files import write_setting

    from monolib.data.hypersim import Camera
    from monolib.io import read_h5, write_h5

    cam = Camera.canonical(64, 48)
    keys = []
    for setting, wall, floor in (("ai_001_001", -1.0, -2.0), ("ai_002_001", -3.0, -2.5)):
        write_setting(root, setting, M=cam.M_cam_from_uv, frames=frames, split="train")
        images = root / setting / "images"
        for i in range(frames):
            geo, fin = images / "scene_cam_00_geometry_hdf5", images / "scene_cam_00_final_hdf5"
            labels = read_h5(geo / f"frame.{i:04d}.semantic.hdf5")
            depth = np.full(labels.shape, 3.0, np.float32)
            depth[:12] = 25.0
            write_h5(geo / f"frame.{i:04d}.depth_meters.hdf5", depth)
            sign = 1 if (i // 2) % 2 else -1
            colour = np.full(labels.shape + (3,), 0.7, np.float32)
            colour[labels == 1] = math.exp(wall + 0.2 * sign)
            colour[labels == 2] = math.exp(floor + 0.1 * sign)
            write_h5(fin / f"frame.{i:04d}.color.hdf5", colour)
            keys.append((setting, f"{setting}/cam_00/{i:04d}"))
    return keys


def hypersim_study(tmp_path, root, projection: str = "exact"):
    import yaml

    from monolib.params import load_study

    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data.update(name="light_test", scenarios={"s1": {"depth": "gt", "semantic": "gt"}},
                graphs={"projection": projection})
    data["dataset"].update(source="hypersim", root=str(root), workers=1, train_frames_per_setting=20)
    data["protocol"].update(settings=2, siblings=0, frames=2, queries=1, positives=1)
    data["gcn"].update(val_settings=0)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(data))
    return load_study(p)


def test_frame_statistics_known_answers_from_hypersim_files(tmp_path, monkeypatch):
    """Pixel depth and HDR colour read from the files: 3 m and 25 m (a quarter beyond 20 m); HDR wall sd 0.2 within
    and 1.0 between the two settings (ratio 5), floor 0.1 and 0.25 (2.5); a missing colour file is counted."""
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    root = tmp_path / "data"
    keys = light_dataset(root)
    study = hypersim_study(tmp_path, root)
    graphs = [Data(setting=s, frame=k, num_nodes=0) for s, k in keys]
    sample = fidelity.light_sample(graphs)
    assert [g.frame for g in sample] == [k for _, k in keys][::2]  # every 2nd, in order
    st = fidelity.frame_statistics(study, sample)
    assert st["pixel depth, frames"] == 20
    assert st["pixel depth, pixels"] == 20 * 48 * 64
    assert st["pixel depth, median"] == 3.0 and st["pixel depth, p90"] == 25.0
    assert st["pixel depth, share beyond 20 m"] == 0.25
    assert st["wall HDR colour sd, within settings"] == pytest.approx(0.2, abs=1e-6)
    assert st["wall HDR colour sd, between settings"] == pytest.approx(1.0, abs=1e-6)
    assert st["wall HDR colour ratio"] == pytest.approx(5.0, abs=1e-4)
    assert st["floor HDR colour sd, within settings"] == pytest.approx(0.1, abs=1e-6)
    assert st["floor HDR colour ratio"] == pytest.approx(2.5, abs=1e-4)
    assert st["frames unreadable"] == 0
    (root / "ai_002_001" / "images" / "scene_cam_00_final_hdf5" / "frame.0004.color.hdf5").unlink()
    again = fidelity.frame_statistics(study, sample)
    assert again["frames unreadable"] == 1 and again["wall HDR colour sd, within settings"] > 0


def original_pair_lengths(root, setting: str, frame: int) -> np.ndarray:
    """The original code's node pair lengths of one frame (GenerateSceneGraph.py, as the shared doc gives it): a
    loop over labels, per-axis medians of x = (j - W // 2) z / f_w, y = (i - H // 2) z / f_h, z = depth_meters."""
    from monolib.io import read_h5

    geo = root / setting / "images" / "scene_cam_00_geometry_hdf5"
    z = read_h5(geo / f"frame.{frame:04d}.depth_meters.hdf5").astype(np.float64)
    sem = read_h5(geo / f"frame.{frame:04d}.semantic.hdf5")
    h, w = z.shape
    fov_y = 2 * math.atan(768 * math.tan(1.0471975803375244 / 2) / 1024)
    f_h = 1000 * math.tan(fov_y / 2) * h / 768
    f_w = 1000 * math.tan(fov_y / 2) * 1024 / 768 * w / 1024
    nodes = []
    for label in sorted(set(sem[(sem >= 1) & np.isfinite(z)].tolist())):
        ii, jj = np.nonzero((sem == label) & np.isfinite(z))
        zz = z[ii, jj]
        nodes.append([np.median((jj - w // 2) * zz / f_w), np.median((ii - h // 2) * zz / f_h), np.median(zz)])
    nodes = np.array(nodes)
    a, b = np.triu_indices(len(nodes), 1)
    return np.linalg.norm(nodes[a] - nodes[b], axis=1)


def test_an_exact_study_measures_its_pairs_in_both_cameras(tmp_path, monkeypatch, capsys):
    """`monolib fidelity` on an `exact` study: its graphs in its own camera, and the same frames built again in the
    original code's camera, whose lengths are those of the original formula on the files; fidelity.md shows both."""
    from monolib import cli
    from monolib.graphs import scenegraphs
    from hypersim_files import write_setting

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    root = tmp_path / "data"
    light_dataset(root)
    for setting in ("ai_003_001", "ai_004_001"):
        write_setting(root, setting, frames=2, split="test")
    study = hypersim_study(tmp_path, root, "exact")
    monograph = fidelity.projected_graphs(study, "s1", "monograph")["train"]
    assert len(monograph) == 40
    for g in monograph[:3]:
        setting, _, index = g.frame.split("/")
        assert g.pair_len.numpy() == pytest.approx(original_pair_lengths(root, setting, int(index)), rel=1e-5)
    exact = scenegraphs.load(study, "s1")["train"]
    assert not np.allclose(exact[0].pair_len.numpy(), monograph[0].pair_len.numpy(), rtol=0.05)
    assert (tmp_path / "runs" / "light_test" / "graphs").glob("s1_monograph-*.pt")
    assert cli.main(["fidelity", str(tmp_path / "study.yaml")]) == 0
    out = capsys.readouterr().out
    assert "| pair length p10 / median / mean / p90 (m), monograph camera |" in out
    assert "| pair length p10 / median / mean / p90 (m), exact camera |" in out
    assert "pixel depth, median in [4, 5.6]: 3.00 FAIL" in out
    assert "wall HDR colour ratio in [2, 4]: 5.0" in out


def test_the_development_set_is_measured_into_the_reference_table_and_nothing_else_moves(tmp_path):
    """`monolib fidelity --reference DIR`: published graph files measured by the study's own statistics, written as
    one source of the reference table; every other row stays byte for byte, and a second measurement replaces the
    first."""
    from test_published import write_folder

    write_folder(tmp_path / "dev" / "train", ["001001", "001002", "002001"], 12, np.random.default_rng(0))
    table = tmp_path / "reference.csv"
    table.write_bytes(fidelity.REFERENCE_CSV.read_bytes())
    before = [line for line in table.read_text().splitlines() if fidelity.DEVELOPMENT not in line]
    stats = fidelity.write_reference(tmp_path / "dev", table)
    assert stats["settings"] == 3 and stats["graphs"] == 36 and fidelity.SETTING_LIGHT in stats
    for k, v in fidelity.split_statistics(published.read_folder(tmp_path / "dev" / "train")).items():
        assert stats[k] == v or (math.isnan(v) and math.isnan(stats[k])), k
    first = table.read_text()
    assert [line for line in first.splitlines() if fidelity.DEVELOPMENT not in line] == before
    ref = fidelity.read_reference(table)
    assert ref[fidelity.DEVELOPMENT]["graphs"] == 36 and ref["real Hypersim, train"]["nodes per graph, mean"] == 8.2
    fidelity.write_reference(tmp_path / "dev", table)
    assert table.read_text() == first
