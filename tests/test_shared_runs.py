"""One runs folder, many runs: two study files of one name and different GCN settings, one after the other and at
once, both keep their cells; a second run of a study waits for the first; a render never deletes another
process's work. (Issue: shared runs folders.)"""
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from monolib import locks, paths
from monolib.data import synth
from monolib.params import load_study
from monolib.report import graph_sizes
from monolib.retrieval import cell

pytestmark = [pytest.mark.slow, pytest.mark.shares_runs]
NAME = "smoke_shared"


def study_file(tmp_path: Path, tag: str, epochs: int) -> Path:
    """The smoke study's ground-truth scenario over its dataset, one cell, under one name for every `tag`."""
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data.update(name=NAME, thresholds=[1], seeds=[0], methods=["gcn"], scenarios={"s1": data["scenarios"]["s1"]})
    data["dataset"]["root"] = str(load_study("smoke").dataset_root)
    data["gcn"]["epochs"] = epochs
    path = tmp_path / f"{tag}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def folder() -> Path:
    return paths.cell_dir(NAME, "gcn", "s1", 1.0, 0)


def record(path: Path) -> dict:
    return json.loads((path / "cell.json").read_text())


@pytest.fixture
def two(smoke_study, tmp_path):
    subprocess.run(["rm", "-rf", str(paths.study_dir(NAME))], check=True)
    a, b = study_file(tmp_path, "a", 2), study_file(tmp_path, "b", 3)
    keys = {p: cell.cell_key(load_study(p), "gcn", "s1", 1.0, 0) for p in (a, b)}
    assert keys[a] != keys[b]
    yield a, b, keys
    subprocess.run(["rm", "-rf", str(paths.study_dir(NAME))], check=True)


def test_two_study_files_of_one_name_one_after_the_other_keep_both_cells(two):
    from monolib.study.runner import prepare

    a, b, keys = two
    prepare(str(a), cells=True, progress=False)
    assert record(folder())["key"] == keys[a]
    made_a = (folder() / "model.pt").read_bytes()
    prepare(str(b), cells=True, progress=False)
    assert record(folder())["key"] == keys[b]                   # b's cell in the folder the report reads
    kept = cell.aside(folder(), keys[a])
    assert record(kept)["key"] == keys[a] and (kept / "model.pt").read_bytes() == made_a   # a's: kept, whole
    stamp = (kept / "cell.json").stat().st_mtime_ns
    prepare(str(a), cells=True, progress=False)                  # a again: its cell moves back, nothing recomputed
    assert record(folder())["key"] == keys[a] and (folder() / "cell.json").stat().st_mtime_ns == stamp
    assert record(cell.aside(folder(), keys[b]))["key"] == keys[b]


def test_two_study_files_of_one_name_at_once_both_finish_and_keep_their_cells(two, tmp_path):
    """Both started while a third run holds the study: each prints one line naming the holder and waits; released,
    one runs while the other waits for it, then the other runs; both finish and both cells remain. (The holder
    makes the overlap certain: two runs started together could otherwise finish one before the other locks.)"""
    a, b, keys = two
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path; "
                               "from monolib import locks\nwith locks.study_lock(Path(sys.argv[1])):\n"
                               "    print('held', flush=True); time.sleep(600)", str(paths.study_dir(NAME))],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        code = "import sys; from monolib.study.runner import prepare; prepare(sys.argv[1], cells=True, progress=False)"
        logs = [tmp_path / f"{p.stem}.err" for p in (a, b)]
        procs = [subprocess.Popen([sys.executable, "-c", code, str(p)], stdout=subprocess.DEVNULL,
                                  stderr=open(log, "w"), env={**os.environ, "MPLBACKEND": "agg"})
                 for p, log in zip((a, b), logs)]
        deadline = time.time() + 300
        while not all(f"in use by pid {holder.pid}" in log.read_text() for log in logs):
            assert time.time() < deadline and all(p.poll() is None for p in procs), [log.read_text() for log in logs]
            time.sleep(0.2)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert [p.wait(timeout=600) for p in procs] == [0, 0], [log.read_text()[-2000:] for log in logs]
    assert all("waiting for it to finish" in log.read_text() for log in logs)
    found = {record(f)["key"] for f in (folder(), *cell.aside(folder(), "x").parent.glob(folder().name + "@*"))}
    assert found == set(keys.values())


def test_a_second_lock_names_the_first_and_a_killed_holder_leaves_none(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from pathlib import Path; "
                               "from monolib import locks\nwith locks.study_lock(Path(sys.argv[1])):\n"
                               "    print('held', flush=True); time.sleep(600)", str(tmp_path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(locks.RunInProgress, match=rf"in use by pid {holder.pid} on {socket.gethostname()}"):
            with locks.study_lock(tmp_path, wait=False):
                pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    with locks.study_lock(tmp_path, wait=False):  # the kernel dropped the dead holder's lock
        with locks.study_lock(tmp_path, wait=False):  # and a lock is re-entrant within its process
            assert str(tmp_path.resolve()) in os.environ[locks.ENV]
    assert str(tmp_path.resolve()) not in os.environ.get(locks.ENV, "")


def test_a_notebook_that_writes_waits_for_the_studys_lock(smoke_study, tmp_path):
    """`notebooks/data.ipynb` renders the dataset when it is missing, so it takes the study's lock as `monolib study`
    does: while another process holds it, the notebook says so and waits, then runs to the end."""
    holder = subprocess.Popen([sys.executable, "-c", "import time; from monolib import locks; from monolib.params "
                               "import load_study\nwith locks.of_study(load_study('smoke')):\n"
                               "    print('held', flush=True); time.sleep(600)"], stdout=subprocess.PIPE, text=True)
    papermill = Path(sys.executable).with_name("papermill")
    try:
        assert holder.stdout.readline().strip() == "held"
        nb = subprocess.Popen([str(papermill), str(paths.NOTEBOOKS / "data.ipynb"), str(tmp_path / "out.ipynb"),
                               "--log-output"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env={**os.environ, "MPLBACKEND": "agg"})
        seen = []
        for line in nb.stdout:  # ends at the notebook's end: a notebook that does not wait fails here
            seen.append(line)
            if "waiting for it to finish" in line:
                break
        assert any(f"in use by pid {holder.pid}" in ln for ln in seen), "".join(seen)[-3000:]
        assert nb.poll() is None  # still waiting
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    rest, _ = nb.communicate(timeout=600)
    assert nb.returncode == 0, rest[-3000:]


def test_a_render_removes_only_the_leftovers_of_ended_processes(smoke_study):
    """`render_dataset` on a rendered dataset beside a render in progress (a living process of this host), one of
    another host, and the leftovers of an ended process and of older code: only the last two go."""
    host = socket.gethostname()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    s = load_study("smoke")
    root = s.dataset_root
    cases = {f".tmp_ai_900_001@{host}@{os.getpid()}": True,       # stays: a living process of this host
             f".tmp_ai_900_002@another-host@{os.getpid()}": True,  # stays: another machine's
             f".tmp_ai_900_003@{host}@{dead.pid}": False,          # goes: an ended process
             ".tmp_ai_900_004_12345": False}                       # goes: the layout of older code
    try:
        for name in cases:
            (root / name).mkdir()
            (root / name / "part.hdf5").write_bytes(b"half a render")
        synth.render_dataset(s, root, progress=False)
        assert {name: (root / name).is_dir() for name in cases} == cases
    finally:
        for name in cases:
            subprocess.run(["rm", "-rf", str(root / name)], check=True)


def test_the_graph_stage_counts_the_labelled_pixels_it_drops_for_their_depth(smoke_study, monkeypatch):
    """A depth source with NaN in a block of each frame: the nodes leave those pixels out, and the frame's count of
    dropped pixels is exactly the labelled pixels of the block (unlabelled ones are not nodes anyway)."""
    import numpy as np

    from monolib.data import dataset, selection
    from monolib.graphs import scenegraphs
    from monolib.perception import predictions

    s = load_study("smoke")
    frame = selection.select_frames(s, dataset.open_dataset(s), s.gcn.val_settings).test[0]
    real = predictions.depth_source

    def with_a_hole(study, name):
        read = real(study, name)

        def holed(f):
            d = read(f).copy()
            d[:40, :50] = np.nan
            return d
        return holed

    monkeypatch.setattr(predictions, "depth_source", with_a_hole)
    x, pos, dropped = scenegraphs._frame_nodes((s, ["s1"], frame.key))[0]
    sem = frame.semantic
    valid_gt = np.isfinite(frame.depth) & (frame.depth > 0)
    expected = int(((sem >= 1) & ~valid_gt).sum() + ((sem[:40, :50] >= 1) & valid_gt[:40, :50]).sum())
    assert dropped == expected and dropped > 0
    sizes = graph_sizes.graph_sizes(s)
    assert {"dropped_pixels", "frames_with_dropped_pixels"} <= set(sizes.columns)
    assert (sizes["dropped_pixels"] >= 0).all()


def test_a_setting_rendered_for_another_study_file_is_kept_aside_and_comes_back(tmp_path):
    """Two study files render into one dataset folder with other keys (here another resolution): the first's
    settings are moved aside, never deleted, and come back unrendered, byte for byte, when it runs again."""
    import copy
    import hashlib

    def tiny(width, height):
        s = copy.deepcopy(load_study("smoke"))
        ds = s.dataset
        ds.width, ds.height, ds.train_settings, ds.test_settings, ds.test_siblings = width, height, 2, 2, 0
        ds.frames_per_setting, ds.train_frames_per_setting, ds.tilt_shift_settings, ds.workers = 2, 2, 0, 1
        return s

    def digest(root):
        return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(root.glob("ai_*/images/*/*.hdf5"))}

    root = tmp_path / "dataset"
    a, b = tiny(128, 96), tiny(64, 48)
    synth.render_dataset(a, root, progress=False)
    first = digest(root)
    assert first
    synth.render_dataset(b, root, progress=False)
    assert digest(root) != first
    assert len(list((root / ".aside").iterdir())) == 4                  # a's four settings, kept whole
    stamp = {p: p.stat().st_mtime_ns for p in root.glob(".aside/*/_detail/monolib_synth_setting.json")}
    synth.render_dataset(a, root, progress=False)                        # back, not rendered again
    assert digest(root) == first
    assert all((root / p.relative_to(root / ".aside").parts[0].split("@")[0] / "_detail" /
                "monolib_synth_setting.json").stat().st_mtime_ns == t for p, t in stamp.items())
    assert len(list((root / ".aside").iterdir())) == 4                  # now b's
