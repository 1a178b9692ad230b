"""Published graph files (the original Monograph release format), written here in that format."""
import math
import re

import numpy as np
import pytest
import torch
import yaml
from torch_geometric.data import Data

from monolib.graphs import published
from monolib.graphs.build import at_threshold
from monolib.graphs.published import PublishedGraphError
from monolib.params import load_study


def published_graph(setting_digits: str, cam: str, frame: int, n: int, rng) -> Data:
    pos = rng.normal(size=(n, 3)) * 2
    i, j = torch.triu_indices(n, n, offset=1)
    length = torch.as_tensor(np.linalg.norm(pos[i.numpy()] - pos[j.numpy()], axis=1), dtype=torch.float32)
    x = torch.as_tensor(np.column_stack([rng.integers(1, 41, n), rng.uniform(0, 1, (n, 3))]), dtype=torch.float32)
    return Data(x=x, edge_index=torch.stack([i, j]), edge_attribute=length[None, :],
                y=[setting_digits, cam, f"{frame:04d}"])


def write_folder(folder, settings, frames, rng):
    folder.mkdir(parents=True, exist_ok=True)
    for s in settings:
        graphs = [published_graph(s, "00", f, int(rng.integers(1, 9)), rng) for f in range(frames)]
        torch.save(graphs, folder / f"ai_{s[:3]}_{s[3:]}_00_graphs.pt")


def test_read_file_filters_lengths_and_makes_edges_undirected(tmp_path):
    rng = np.random.default_rng(0)
    write_folder(tmp_path, ["001002"], 3, rng)
    raw = torch.load(tmp_path / "ai_001_002_00_graphs.pt", weights_only=False)
    graphs = published.read_file(tmp_path / "ai_001_002_00_graphs.pt")
    assert graphs[0].setting == "ai_001_002" and graphs[0].frame == "ai_001_002/cam_00/0000"
    for g, r in zip(graphs, raw):
        t = 2.0
        keep = r.edge_attribute[0] < t
        g2 = at_threshold(g, t)
        assert g2.edge_index.shape[1] == 2 * int(keep.sum())
        pairs = set(map(tuple, g2.edge_index.t().tolist()))
        assert all((b, a) in pairs for a, b in pairs)
        assert at_threshold(g, math.inf).edge_index.shape[1] == 2 * r.edge_index.shape[1]


def test_bad_files_name_the_file(tmp_path):
    bad = tmp_path / "ai_001_001_00_graphs.pt"
    bad.write_bytes(b"not torch")
    with pytest.raises(PublishedGraphError, match="ai_001_001_00_graphs.pt: not a readable torch file"):
        published.read_file(bad)
    with pytest.raises(PublishedGraphError, match="ai_VVV_NNN_XX_graphs.pt"):
        published.read_file(tmp_path / "graphs.pt")


def _without(attr):
    def change(g):
        del g[attr]
    return change


def _edges(pairs, lengths=None):
    def change(g):
        g.edge_index = torch.tensor(pairs, dtype=torch.long).t().reshape(2, -1)
        n = len(pairs) if lengths is None else lengths
        g.edge_attribute = torch.ones((1, n))
    return change


# (what the file holds instead of the release's format, the error's words after "<file>: ")
BAD_FILES = {
    "not a list": ("dict", "expected a list of torch_geometric Data, got dict"),
    "no edge_attribute": (_without("edge_attribute"), "graph 1: no 'edge_attribute' (expected x, edge_index"),
    "no y": (_without("y"), "graph 1: no 'y'"),
    "edges and lengths differ": (_edges([(0, 1), (0, 2), (1, 2)], lengths=2),
                                 "graph 1: 3 edges and 2 lengths; expected one length per edge"),
    "i > j": (_edges([(0, 1), (2, 1)]), "graph 1: pair (2, 1) at edge 1 has i > j; expected pairs i < j only"),
    "self-loop": (_edges([(0, 1), (2, 2)]), "graph 1: self-loop (2, 2) at edge 1; expected pairs of two different"),
    "both directions": (_edges([(0, 1), (1, 2), (1, 0)]),
                        "graph 1: pair (0, 1) is listed in both directions; expected each pair once, as i < j"),
    "listed twice": (_edges([(0, 1), (0, 1)]), "graph 1: pair (0, 1) is listed 2 times; expected each pair once"),
    "node out of range": (_edges([(0, 1), (1, 7)]), "graph 1: edge_index refers to node 7; expected node indices 0..2"),
    "y of another file": (lambda g: setattr(g, "y", ["009009", "00", "0001"]),
                          "graph 1: y is ['009009', '00', '0001']; expected ['001001', '00', frame digits]"),
}


def write_bad_file(folder, case):
    """ai_001_001_00_graphs.pt in the release's format, but graph 1 (of 3 nodes) broken as `case` says."""
    change, _ = BAD_FILES[case]
    rng = np.random.default_rng(3)
    graphs = [published_graph("001001", "00", f, 3, rng) for f in range(3)]
    if change == "dict":
        obj = {"graphs": graphs}
    else:
        change(graphs[1])
        obj = graphs
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(obj, folder / "ai_001_001_00_graphs.pt")
    return folder / "ai_001_001_00_graphs.pt"


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_each_bad_published_file_is_one_error_naming_it(tmp_path, case):
    path = write_bad_file(tmp_path, case)
    with pytest.raises(PublishedGraphError, match=f"^{re.escape(f'{path}: {BAD_FILES[case][1]}')}"):
        published.read_file(path)
    # a good file of the same kind reads: the error is the broken graph's, not the reader's habit
    good = tmp_path / "good" / "ai_001_001_00_graphs.pt"
    good.parent.mkdir()
    graphs = [published_graph("001001", "00", f, 3, np.random.default_rng(3)) for f in range(3)]
    torch.save(graphs, good)
    read = published.read_file(good)
    assert [g.pair_index.tolist() for g in read] == [g.edge_index.tolist() for g in graphs]


def test_empty_or_missing_folder_is_one_error(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no graphs here")
    with pytest.raises(PublishedGraphError, match=f"^{re.escape(str(tmp_path / 'empty'))}: no published graph files"):
        published.read_folder(tmp_path / "empty")
    with pytest.raises(PublishedGraphError, match=f"^{re.escape(str(tmp_path / 'nope'))}: folder not found"):
        published.read_folder(tmp_path / "nope")


def published_study(tmp_path, graphs_root, **protocol):
    from monolib import paths

    study = yaml.safe_load((paths.PARAMS / "published.yaml").read_text())
    study.update(name="published_test", graphs_root=str(graphs_root), seeds=[0], thresholds=[1])
    study.pop("variants", None)  # one cell in all: a reader that let a bad file through fails the test in seconds
    study["protocol"].update(settings=3, frames=5, queries=3, positives=2, **protocol)
    study["gcn"].update(epochs=1, min_epochs=1, val_settings=1)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(study))
    return p


@pytest.mark.parametrize("case", sorted(BAD_FILES) + ["empty train folder"])
def test_the_command_says_error_and_exits_2_on_bad_published_graphs(tmp_path, monkeypatch, capsys, case):
    """`monolib study` on a published-graphs study with one bad file: exit status 2 and one `error:` line naming
    the file and what was expected, no traceback, before any cell runs."""
    from monolib import cli, paths

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    root = tmp_path / "graphs"
    write_folder(root / "test", [f"01{i}001" for i in range(1, 4)], 5, np.random.default_rng(1))
    if case == "empty train folder":
        (root / "train").mkdir()
        where, message = root / "train", "no published graph files; expected ai_VVV_NNN_XX_graphs.pt files"
    else:
        write_folder(root / "train", [f"00{i}001" for i in range(2, 4)], 6, np.random.default_rng(2))
        where, message = write_bad_file(root / "train", case), BAD_FILES[case][1]
    code = cli.main(["study", str(published_study(tmp_path, root))])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"error: {where}: {message}"), lines[0]
    assert not (tmp_path / "runs" / "published_test" / "cells").exists()


def test_a_published_study_runs_a_cell(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    write_folder(tmp_path / "graphs" / "train", [f"00{i}001" for i in range(1, 6)], 6, rng)
    write_folder(tmp_path / "graphs" / "test", [f"01{i}001" for i in range(1, 4)], 5, rng)
    from monolib import paths

    study = yaml.safe_load((paths.PARAMS / "published.yaml").read_text())
    study.update(name="published_test", graphs_root=str(tmp_path / "graphs"))
    study["protocol"].update(settings=3, frames=5, queries=3, positives=2)
    study["gcn"].update(epochs=2, min_epochs=1, val_settings=1)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(study))
    s = load_study(p)
    from monolib import paths
    from monolib.retrieval import cell

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    result = cell.run_cell(s, "gcn", "s1", 2.0, 0, out_dir=str(tmp_path / "cell"))
    assert list(result["metrics"]) == ["paper"]    # published.yaml: protocol.siblings 0, the paper protocol only
    assert set(result["metrics"]["paper"]) == {"recall@1", "recall@5", "recall@10", "precision@2", "precision@4",
                                               "precision@6"}
    assert (tmp_path / "cell" / "rankings.csv").exists()
    # threshold 0: no edges, the encoder sees the nodes only; a negative threshold is one clear error
    zero = cell.run_cell(s, "gcn", "s1", 0.0, 0, out_dir=str(tmp_path / "zero"))
    assert zero["threshold"] == 0.0 and zero["test_edges_mean"] == 0.0 and zero["test_nodes_mean"] > 0
    assert 0 <= zero["metrics"]["paper"]["recall@1"] <= 100
    from monolib.params import StudyError

    with pytest.raises(StudyError, match="threshold -1.0: expected 0 \\(no edges\\)"):
        cell.run_cell(s, "gcn", "s1", -1.0, 0, out_dir=str(tmp_path / "negative"))
    # the study file's encoder variants run on published graphs too (label embedding, GINE on lengths, batch-hard)
    edges = {}
    for method in ("ours", "gine", "batch_hard", "gcn_undirected"):
        r = cell.run_cell(s, method, "s1", 1.0, 0, out_dir=str(tmp_path / method))
        assert r["method"] == method and 0 <= r["metrics"]["paper"]["recall@1"] <= 100
        edges[method] = r["test_edges_mean"]
    # the paper's encoder and its one-part ablations (gine, batch_hard) read each pair once, i < j; `ours` and the
    # undirected ablation both directions
    assert edges["ours"] == edges["gcn_undirected"] == 2 * edges["gine"] == 2 * edges["batch_hard"] > 0
    # quick's `layout` encoder on published graphs: its pair readout reads their lengths (no positions), every pair
    r = cell.run_cell(s, "layout", "s1", float("inf"), 0, out_dir=str(tmp_path / "layout"))
    assert r["encoder"]["pair_readout"] and not (r["encoder"]["edge_layout"] or r["encoder"]["node_layout"])
    assert r["test_edges_mean"] >= edges["ours"] and 0 <= r["metrics"]["paper"]["recall@1"] <= 100


SAMPLE = (published.Path(__file__).resolve().parents[2] / "shared" / "data" / "published_graphs_sample"
          / "ai_001_001_00_graphs.pt")


@pytest.mark.skipif(not SAMPLE.exists(), reason="shared published graph sample absent")
def test_the_real_published_sample():
    graphs = published.read_file(SAMPLE)
    assert len(graphs) == 98 and all(g.setting == "ai_001_001" for g in graphs)
    g = graphs[0]
    assert g.pair_index.shape[1] == g.num_nodes * (g.num_nodes - 1) // 2  # the release stores every pair once
    assert at_threshold(g, 1.0).edge_index.shape[1] < at_threshold(g, math.inf).edge_index.shape[1]


def test_published_test_settings_follow_both_protocols(tmp_path):
    """Published graphs are selected by the rule of a dataset: paper = settings in turn from each volume (here one
    per volume, there being as many volumes as settings), siblings = both settings of a volume; a volume with one
    setting cannot give a sibling pair."""
    rng = np.random.default_rng(2)
    write_folder(tmp_path / "graphs" / "train", [f"00{i}001" for i in range(1, 4)], 3, rng)
    write_folder(tmp_path / "graphs" / "test", ["011001", "011002", "012001", "013001", "013002"], 4, rng)
    from monolib import paths

    study = yaml.safe_load((paths.PARAMS / "published.yaml").read_text())
    study.update(name="published_test", graphs_root=str(tmp_path / "graphs"))
    study["protocol"].update(settings=3, siblings=1, frames=4, queries=3, positives=1)
    study["gcn"].update(val_settings=1)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(study))
    test = published.select(load_study(p))["test"]
    assert sorted({g.setting for g in test}) == ["ai_011_001", "ai_011_002", "ai_012_001", "ai_013_001"]
    study["protocol"].update(siblings=3)
    p.write_text(yaml.safe_dump(study))
    with pytest.raises(ValueError, match="families without a sibling: ai_012"):
        published.select(load_study(p))


def test_a_release_of_three_volumes_gives_the_paper_protocol_its_16_settings(tmp_path, monkeypatch):
    """The original release's test split: 50 files of 39 settings from three volumes only (ai_024, ai_026,
    ai_027; 11 settings with a second camera), each setting with 41 frames or more. The paper took 16 settings of
    it; here the `paper` protocol takes them in turn from each volume (6, 5, 5), a cell runs on them, and the
    table caption says how they were chosen. On the mini-Hypersim (families by construction) the rule of
    different families stays: the same names there are refused."""
    rng = np.random.default_rng(3)
    test = tmp_path / "graphs" / "test"
    test.mkdir(parents=True)
    settings = [f"{v}{n:03d}" for v, count in (("024", 13), ("026", 13), ("027", 13)) for n in range(1, count + 1)]
    for k, s in enumerate(settings):
        cams = ["00", "01"] if k % 4 == 0 else ["00"]  # 10 settings x 2 cameras + 29 x 1 = 49 files
        cams += ["02"] if k == 1 else []                          # and one third camera: 50 files
        for c, cam in enumerate(cams):
            graphs = [published_graph(s, cam, f, int(rng.integers(1, 6)), rng) for f in range(41 if c == 0 else 8)]
            torch.save(graphs, test / f"ai_{s[:3]}_{s[3:]}_{cam}_graphs.pt")
    assert len(list(test.iterdir())) == 50
    write_folder(tmp_path / "graphs" / "train", [f"0{i:02d}001" for i in range(1, 6)], 6, rng)
    from monolib import paths
    from monolib.data.protocols import ProtocolDataError, protocol_settings
    from monolib.report import tables
    from monolib.retrieval import cell

    study = yaml.safe_load((paths.PARAMS / "published.yaml").read_text())
    study.update(name="published_release", graphs_root=str(tmp_path / "graphs"), seeds=[0], thresholds=[1])
    study.pop("variants")
    study["gcn"].update(epochs=1, min_epochs=1, val_settings=1)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(study))
    s = load_study(p)
    assert s.protocol.settings == 16 and s.protocol.families is False      # published.yaml as shipped
    chosen = sorted({g.setting for g in published.select(s)["test"]})
    assert len(chosen) == 16
    assert [sum(c.startswith(f"ai_{v}_") for c in chosen) for v in ("024", "026", "027")] == [6, 5, 5]
    assert chosen[:3] == ["ai_024_001", "ai_024_002", "ai_024_003"]
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    result = cell.run_cell(s, "gcn", "s1", 1.0, 0, out_dir=str(tmp_path / "cell"))
    assert list(result["metrics"]) == ["paper"]
    import pandas as pd

    drawn = pd.read_csv(tmp_path / "cell" / "protocol.csv")  # the cell drew its queries from those 16 settings
    assert sorted(drawn["setting"].unique()) == chosen
    assert "16 test settings taken in turn from each volume" in tables.protocol_note("paper", s.protocol)
    # the mini-Hypersim's rule on the same names: one setting per family, refused with three families
    s.protocol.families = True
    with pytest.raises(ProtocolDataError, match="found 3 families among 39 such settings"):
        protocol_settings([f"ai_{x[:3]}_{x[3:]}" for x in settings], s.protocol)
