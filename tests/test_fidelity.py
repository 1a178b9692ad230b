"""Data fidelity (monolib.graphs.fidelity): known answers on hand-built graphs, agreement with the shared reference script,
and the real published sample."""
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
    study = type("S", (), {"name": "empty_test"})()
    _, md = fidelity.write(study, {"this study, train": fidelity.split_statistics([]), "this study, test": stats})
    text = md.read_text()
    assert "NaN / NaN / NaN / NaN" in text and "0 of 11 pass" in text and "wall colour ratio >= 2.0: NaN FAIL" in text


def test_reference_file_is_read_and_the_tables_are_written(tmp_path, monkeypatch):
    ref = fidelity.read_reference()
    assert ref["real Hypersim, train"]["nodes per graph, mean"] == 8.2
    assert ref["real Hypersim, test"]["floor colour ratio"] == 4.3
    assert ref["real Hypersim, train"]["label frequency, wall"] == 0.91
    assert len([k for k in ref["real Hypersim, train"] if k.startswith("label frequency")]) == 20
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    study = type("S", (), {"name": "table_test"})()
    stats = fidelity.split_statistics(two_settings())
    csv_path, md_path = fidelity.write(study, {"this study, train": stats, "this study, test": stats})
    assert csv_path.parent == paths.figures_dir("table_test") == tmp_path / "runs" / "table_test" / "figures"
    import csv

    rows = list(csv.DictReader(csv_path.open()))
    assert {r["source"] for r in rows} == {"this study, train", "this study, test", "real Hypersim, train",
                                          "real Hypersim, test"}
    value = {(r["statistic"], r["source"]): float(r["value"]) for r in rows}
    assert value[("wall colour ratio", "this study, train")] == pytest.approx(5.0, abs=1e-4)
    assert value[("nodes per graph, mean", "real Hypersim, test")] == 2.8
    md = md_path.read_text()
    assert ("| nodes per graph: mean / median / p10 / p90 | 3.0 / 3 / 3 / 3 | 3.0 / 3 / 3 / 3 | 8.2 / 9 / 3 / 12 "
            "| 2.8 / 2 / 1 / 6 |") in md
    assert "| wall colour sd within / between settings (ratio) | 0.20 / 1.00 (5.0) |" in md
    assert "| label-set Jaccard within / across settings | 1.00 / 0.50 |" in md
    assert "real Hypersim, train (169 settings)" in md and "this study, train (2 settings)" in md
    assert "Label frequency, real Hypersim, train (share of graphs): wall 0.91, floor 0.86, otherprop 0.73" in md
    assert "Label frequency, this study, train (share of graphs): wall 1.00, floor 1.00, cabinet 0.50, bed 0.50." in md
    assert "nodes per graph mean 7-10: 3.0 FAIL" in md and "wall colour ratio >= 2.0: 5.0 pass" in md
    assert "floor colour ratio >= 2.0:" in md and "wall in >= 30% of graphs: 1.00 pass" in md
    assert "otherprop in >= 30% of graphs: 0.00 FAIL" in md


def test_acceptance_targets_pass_when_met():
    stats = {"nodes per graph, mean": 8.0, "label-set Jaccard, within settings": 0.7,
             "label-set Jaccard, across settings": 0.3, "wall colour ratio": 2.5, "floor colour ratio": 2.0}
    stats.update({fidelity.frequency_name(n): 0.3 for n in fidelity.TARGET_FREQUENT})
    assert all(ok for _, ok in fidelity.acceptance(stats))
    stats["label-set Jaccard, across settings"] = 0.41
    assert [ok for _, ok in fidelity.acceptance(stats)].count(False) == 1


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


def test_a_study_cache_through_the_command(tmp_path, monkeypatch, capsys):
    """`monolib fidelity STUDY` reads the study's ground-truth graph cache and writes both files."""
    from monolib import cli
    from monolib.graphs import stage as scenegraphs
    from monolib.params import load_study

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    study = load_study("smoke")
    assert fidelity.ground_truth_scenario(study) == "s1"
    path = scenegraphs.graphs_path(study, "s1")
    path.parent.mkdir(parents=True)
    torch.save({"scenario": "s1", "graphs": {"train": two_settings(), "val": [], "test": two_settings()[:10]},
                "seconds": 0.0}, path)
    assert cli.main(["fidelity", "smoke"]) == 0
    out = capsys.readouterr().out
    assert "| label-set Jaccard within / across settings | 1.00 / 0.50 | 1.00 / NaN |" in out
    assert (paths.figures_dir("smoke") / "fidelity.csv").is_file()
    assert (paths.figures_dir("smoke") / "fidelity.md").read_text() in out


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
