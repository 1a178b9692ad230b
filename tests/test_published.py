"""Published graph files (the original Monograph release format), written here in that format."""
import math

import numpy as np
import pytest
import torch
import yaml
from torch_geometric.data import Data

from monolib import published
from monolib.params import load_study
from monolib.graph import at_threshold


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
    with pytest.raises(ValueError, match="ai_001_001_00_graphs.pt"):
        published.read_file(bad)
    with pytest.raises(ValueError, match="ai_VVV_NNN_XX_graphs.pt"):
        published.read_file(tmp_path / "graphs.pt")


def test_a_published_study_runs_a_cell(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    write_folder(tmp_path / "graphs" / "train", [f"00{i}001" for i in range(1, 6)], 6, rng)
    write_folder(tmp_path / "graphs" / "test", [f"01{i}001" for i in range(1, 4)], 5, rng)
    from monolib import paths

    study = yaml.safe_load((paths.PARAMS / "published.yaml").read_text())
    study.update(name="published_test", graphs_root=str(tmp_path / "graphs"))
    study["protocol"].update(settings=3, frames=5, queries=3, positives=2)
    study["gcn"].update(epochs=2, val_settings=1)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(study))
    s = load_study(p)
    from monolib import cell, paths

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
    for method in ("ours", "gine", "batch_hard", "gcn_published"):
        r = cell.run_cell(s, method, "s1", 1.0, 0, out_dir=str(tmp_path / method))
        assert r["method"] == method and 0 <= r["metrics"]["paper"]["recall@1"] <= 100


SAMPLE = published.Path(__file__).resolve().parents[2] / "shared" / "data" / "published_graphs_sample" / "ai_001_001_00_graphs.pt"


@pytest.mark.skipif(not SAMPLE.exists(), reason="shared published graph sample absent")
def test_the_real_published_sample():
    graphs = published.read_file(SAMPLE)
    assert len(graphs) == 98 and all(g.setting == "ai_001_001" for g in graphs)
    g = graphs[0]
    assert g.pair_index.shape[1] == g.num_nodes * (g.num_nodes - 1) // 2  # the release stores every pair once
    assert at_threshold(g, 1.0).edge_index.shape[1] < at_threshold(g, math.inf).edge_index.shape[1]


def test_published_test_settings_follow_both_protocols(tmp_path):
    """Published graphs are selected by the same rule as a dataset: paper = one setting per volume (family),
    siblings = both settings of a volume; a volume with one setting cannot give a sibling pair."""
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
