"""Scene graph files in the format of the graphs published with the original Monograph code, written here (the
release itself is not in this repository): ``<root>/<split>/ai_VVV_NNN_XX_graphs.pt``, each a `torch.save`d list
of `Data` with `x` [N, 4] (NYU40 id, R, G, B), `edge_index` [2, E] of every pair i < j once, `edge_attribute`
[1, E] (lengths in metres) and `y` = ['VVVNNN', 'XX', 'IIII'].

Run as a script it writes a release-sized folder for `monolib.bench`'s fold timing:
``python tests/published_files.py <root>`` (259 training files of about 100 graphs, 50 test files).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
import yaml
from torch_geometric.data import Data


def graph(setting_digits: str, cam: str, frame: int, n: int, rng, palette: np.ndarray) -> Data:
    """One frame's graph of `n` nodes: labels and colours drawn around the setting's `palette` (so that settings
    differ and frames of one setting look alike), every pair i < j with its length."""
    pos = rng.normal(size=(n, 3)) * 2
    i, j = torch.triu_indices(n, n, offset=1)
    length = torch.as_tensor(np.linalg.norm(pos[i.numpy()] - pos[j.numpy()], axis=1), dtype=torch.float32)
    rows = palette[rng.integers(0, len(palette), n)]
    x = torch.as_tensor(np.column_stack([rows[:, 0], rows[:, 1:] + rng.normal(0, 0.02, (n, 3))]), dtype=torch.float32)
    return Data(x=x, edge_index=torch.stack([i, j]), edge_attribute=length[None, :],
                y=[setting_digits, cam, f"{frame:04d}"])


def write_release(root: Path, layout: dict[str, dict[str, int]], cameras: int, frames: int, seed: int = 0,
                  nodes: tuple[int, int] = (2, 9)) -> list[Path]:
    """Write ``{split: {'VVV_NNN': settings ... }}``: each setting ``ai_VVV_NNN`` of `layout[split]` gets `cameras`
    files of `frames` graphs (its value: unused, 1). Returns the files written."""
    rng = np.random.default_rng(seed)
    out = []
    for split, settings in layout.items():
        (root / split).mkdir(parents=True, exist_ok=True)
        for name in settings:
            digits = name.replace("_", "")
            palette = np.column_stack([rng.integers(1, 41, 6), rng.uniform(0, 1, (6, 3))])
            for cam in range(cameras):
                gs = [graph(digits, f"{cam:02d}", cam * frames + f, int(rng.integers(*nodes)), rng, palette)
                      for f in range(frames)]
                path = root / split / f"ai_{name}_{cam:02d}_graphs.pt"
                torch.save(gs, path)
                out.append(path)
    return out


def study_file(tmp_path: Path, root: Path, **protocol) -> Path:
    """A published-graphs study on `root` with a small protocol (2 test settings of 4 frames) and a tiny GCN."""
    spec = {"name": "folds_test", "seed": 0, "graphs_root": str(root),
            "dataset": {"source": "hypersim", "train_frames_per_setting": 4},
            "scenarios": {"s1": {"depth": "gt", "semantic": "gt"}}, "thresholds": [1, 2], "seeds": [0],
            "methods": ["gcn"], "gcn": {"epochs": 1, "hidden": 8, "out": 4, "layers": 1, "val_settings": 2,
                                         "batch_size": 8},
            "protocol": {"settings": 2, "frames": 4, "queries": 3, "positives": 1, **protocol}}
    path = tmp_path / "folds_test.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def layout(volumes: list[int], settings: int, test_volumes: list[int]) -> dict[str, dict[str, int]]:
    """`settings` settings per volume, the `test_volumes` in test/ and the others in train/."""
    out: dict[str, dict[str, int]] = {"train": {}, "test": {}}
    for v in volumes:
        for n in range(1, settings + 1):
            out["test" if v in test_volumes else "train"][f"{v:03d}_{n:03d}"] = 1
    return out


def release_size(root: Path, seed: int = 0) -> list[Path]:
    """A folder of the release's size: 259 training files of 100 graphs (26 volumes ... as many settings as it
    takes, 2 cameras each) and 50 test files; graphs of 2..14 nodes (the release's 8 on average in training)."""
    vols = list(range(1, 28))
    test = [24, 26, 27]
    lay = {"train": {}, "test": {}}
    for split, want in (("train", 259), ("test", 50)):
        names = [f"{v:03d}_{n:03d}" for n in range(1, 30) for v in vols if (v in test) == (split == "test")]
        lay[split] = {n: 1 for n in names[: (want + 1) // 2]}
    files = write_release(root, lay, cameras=2, frames=100, seed=seed, nodes=(2, 15))
    return files


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python tests/published_files.py <folder to write train/ and test/ into>")
    print(f"{len(release_size(Path(sys.argv[1])))} files written under {sys.argv[1]}")
