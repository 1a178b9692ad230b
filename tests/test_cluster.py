"""The grid on a Dask cluster started as a user starts one (`dask scheduler`, `dask worker --nworkers 2`): the
same files as the local path, a worker killed in the middle of a cell, and workers that do not match the client."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from monolib import paths
from monolib.params import StudyError, load_study

pytestmark = [pytest.mark.slow, pytest.mark.reads_smoke_cells]
MONOLIB = [sys.executable, "-m", "monolib.cli"]
DASK = str(Path(sys.executable).parent / "dask")
ENV = {**os.environ, "MPLBACKEND": "agg"}


def wait_for(condition, seconds: float, what: str):
    deadline = time.time() + seconds
    while time.time() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"timed out after {seconds} s waiting for {what}")


@pytest.fixture(scope="module")
def scheduler_file(tmp_path_factory):
    """A scheduler and two single-threaded worker processes (under one nanny each), on the loopback interface."""
    from distributed import Client

    d = tmp_path_factory.mktemp("dask")
    path = d / "scheduler.json"
    log = open(d / "cluster.log", "w")
    common = ["--host", "127.0.0.1", "--scheduler-file", str(path)]
    procs = [subprocess.Popen([DASK, "scheduler", *common, "--port", "0", "--dashboard-address", ":0"], env=ENV,
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)]
    wait_for(path.is_file, 60, "the scheduler file")
    procs.append(subprocess.Popen([DASK, "worker", *common, "--nworkers", "2", "--nthreads", "1", "--no-dashboard",
                                   "--local-directory", str(d / "workers")], env=ENV, stdout=log,
                                  stderr=subprocess.STDOUT, start_new_session=True))
    with Client(scheduler_file=str(path), timeout=60) as client:
        client.wait_for_workers(2, timeout=120)
    yield path
    for p in procs:
        os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
    log.close()


def ground_truth_study(tmp_path, name: str, thresholds: list, seeds: list) -> Path:
    """A study over the smoke study's dataset with its ground-truth scenario only (no perception to train)."""
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data.update(name=name, thresholds=thresholds, seeds=seeds, jobs=2, scenarios={"s1": data["scenarios"]["s1"]})
    data["dataset"]["root"] = str(load_study("smoke").dataset_root)
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data))
    subprocess.run(["rm", "-rf", str(paths.study_dir(name))], check=True)
    return path


def cell_records(study: str) -> dict:
    return {f.parent.name: f for f in (paths.study_dir(study) / "cells" / "gcn").glob("*/cell.json")}


def same_cell(a: Path, b: Path) -> None:
    """Two runs of one cell: the same metrics, rankings, protocol draw and embeddings."""
    ra, rb = json.loads(a.read_text()), json.loads(b.read_text())
    assert ra["metrics"] == rb["metrics"] and ra["best_epoch"] == rb["best_epoch"]
    for name in ("rankings.csv", "protocol.csv", "history.csv", "embeddings.npy", "model.pt"):
        assert (a.parent / name).read_bytes() == (b.parent / name).read_bytes(), name


def test_the_grid_on_dask_workers_gives_the_local_files_and_a_killed_worker_costs_its_cell_only(
        smoke_study, scheduler_file, tmp_path):
    """The grid on two Dask workers, one of them SIGKILLed during a cell that started after another cell finished:
    the scheduler hands the cell to a worker again (the nanny restarts the dead one), the study completes, the
    finished cells are not run again, and every cell, the re-run one among them, has the files of the smoke study's
    own cell, run on the local process pool."""
    from distributed import Client

    study_file = ground_truth_study(tmp_path, "smoke_dask_kill", [0, 1, 2, 5, 10], [0])
    proc = subprocess.Popen(MONOLIB + ["study", str(study_file), "--scheduler", str(scheduler_file)], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        with Client(scheduler_file=str(scheduler_file), timeout=60) as client:
            before: set = set()  # the cells started when the first one finished: they may be about to end

            def running_cell():  # (worker, cell) of a cell started after the first cell finished, still running
                done = cell_records("smoke_dask_kill")
                started = {p.stem.removeprefix("gcn__") for p in
                           (paths.study_dir("smoke_dask_kill") / "notebooks" / "cells").glob("*.ipynb")}
                if not done:
                    return None
                if not before:
                    before.update(started)
                for name in sorted(started - before - set(done)):
                    for w, keys in client.processing().items():
                        if any(k.startswith(f"cell gcn/{name} ") for k in keys):
                            return w, name
                return None

            worker, killed = wait_for(running_cell, 600, "a worker starting a cell after a first cell finished")
            done = {name: f.stat().st_mtime_ns for name, f in cell_records("smoke_dask_kill").items()}
            assert killed not in done  # started within the last poll: its kernel is still starting or computing
            pid = client.run(os.getpid, workers=[worker])[worker]
            os.kill(pid, signal.SIGKILL)
        out, _ = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, out[-3000:]
    assert "cells on 2 Dask workers" in out
    after = cell_records("smoke_dask_kill")
    assert len(after) == 5 and 1 <= len(done) < 5 and killed in after
    assert all(after[name].stat().st_mtime_ns == t for name, t in done.items())  # finished: not run again
    local = cell_records("smoke")
    for name, record in after.items():  # each as the local pool ran it (the killed cell as an uninterrupted run)
        same_cell(record, local[name])


def _changed(part: str):
    """A `fingerprint` function of this side only, one part changed: the workers keep the real one."""
    from monolib.study import cluster

    real = cluster.fingerprint

    def fake(study_file):
        f = real(study_file)
        if part == "code":
            f["code"]["graphs"] = "another version"
        elif part == "library":
            f["libraries"]["torch_geometric"] = "0.0.1"
        else:
            f["study"] = "another study"
        return f
    return fake


WORDS = {"code": "code of the graphs stage", "library": r"torch_geometric \S+ \(client 0.0.1\)",
         "study": "the study as loaded"}


@pytest.mark.parametrize("part", sorted(WORDS))
def test_workers_that_compute_otherwise_are_refused_before_any_cell(scheduler_file, tmp_path, monkeypatch, part):
    """Any stage's code (not only the cells'), a library's version, or the study as loaded (its `extends` base
    resolved): each is one problem per worker, before any cell."""
    from monolib.study import cluster

    study_file = ground_truth_study(tmp_path, "smoke_dask_refused", [1], [0])
    monkeypatch.setattr(cluster, "fingerprint", _changed(part))
    with pytest.raises(StudyError, match=rf"2 problem\(s\) with the workers:(\n  tcp://127.0.0.1:\d+: computes cells "
                                         rf"otherwise: {WORDS[part]}.*){{2}}"):
        cluster.connect(str(scheduler_file), load_study(str(study_file)))


@pytest.mark.parametrize("part", sorted(WORDS))
def test_each_task_checks_its_worker_again_before_it_computes(tmp_path, part):
    """What a worker computes with may change after the connection check (a `git pull` on a shared file system, a
    library upgraded under a running worker): the task compares afresh and refuses before the notebook runs."""
    import json

    from monolib.retrieval.grid import CellSpec
    from monolib.study import cluster, notebooks

    study_file = ground_truth_study(tmp_path, "smoke_dask_task", [1], [0])
    client_side = json.dumps(_changed(part)(str(study_file)))
    env = {**cluster.task_environment(), cluster.FINGERPRINT_ENV: client_side}
    out = tmp_path / "cell.ipynb"
    with pytest.raises(StudyError, match=rf"no longer computes cells as the client: {WORDS[part]}"):
        notebooks.run_cell_notebook(str(study_file), CellSpec("gcn", "s1", 1.0, 0), str(out), 60, env)
    assert not out.exists()                                          # refused before the notebook ran
    cluster.check_fingerprint(str(study_file), json.dumps(cluster.fingerprint(str(study_file))))  # the same: passes


@pytest.mark.parametrize("value, words", [("no_such_scheduler.json", "neither a scheduler file (no such file) nor "
                                           "an address"), ("tcp://127.0.0.1", "expected an address with a port")])
def test_a_bad_scheduler_value_is_one_clear_error(tmp_path, capsys, value, words):
    """Through the command's own entry point in this process (an uncaught exception would fail the test)."""
    from monolib import cli

    study_file = ground_truth_study(tmp_path, "smoke_dask_bad", [1], [0])
    capsys.readouterr()
    assert cli.main(["study", str(study_file), "--scheduler", value]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: --scheduler {value}: {words}") and err.count("\n") == 1, err[-2000:]


def test_no_scheduler_at_the_address_is_one_clear_error(tmp_path, capsys, monkeypatch):
    from monolib import cli
    from monolib.study import cluster

    study_file = ground_truth_study(tmp_path, "smoke_dask_none", [1], [0])
    with pytest.raises(StudyError, match="no Dask scheduler answered within 3 s"):
        cluster.connect("tcp://127.0.0.1:9", load_study(str(study_file)), timeout=3)
    monkeypatch.setenv("MONOLIB_CONNECT_SECONDS", "2")
    capsys.readouterr()
    assert cli.main(["study", str(study_file), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --scheduler tcp://127.0.0.1:9: no Dask scheduler answered within 2 s"), err[-2000:]
