"""The smoke study end to end through the real command, resumption after a kill, and a papermill cell run as a
user would, with a threshold and seed that no study file lists."""
import json
import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pandas as pd
import papermill
import pytest
import yaml

from monolib import paths
from monolib.params import load_study
from monolib.report import graph_sizes
from monolib.report.results import check_protocols, recompute_metrics, split_protocols

pytestmark = [pytest.mark.slow, pytest.mark.shares_runs]
MONOLIB = [sys.executable, "-m", "monolib.cli"]
ENV = {**os.environ, "MPLBACKEND": "agg"}


def cell_files(study: str):
    return sorted((paths.study_dir(study) / "cells").glob("*/*/cell.json"))


def test_smoke_study_writes_every_table_and_figure(smoke_study):
    s = load_study("smoke")
    fig = paths.figures_dir("smoke")
    for name in ["results.csv", "table1_recall.md", "table1_recall.tex", "table1_recall.csv", "table2_precision.md",
                 "table2_precision.tex", "table2_precision.csv", "recall_vs_threshold.png", "fig5_matches.png",
                 "perception.csv", "table1_recall_siblings.md", "table1_recall_siblings.tex",
                 "table1_recall_siblings.csv", "table2_precision_siblings.md", "table2_precision_siblings.csv",
                 "table2_precision_siblings.tex", "fig_protocols.png", "protocols.csv", "protocols.md",
                 "graph_sizes.csv", "graph_sizes.md", "intervals.csv"]:
        assert (fig / name).is_file(), name
    results = pd.read_csv(fig / "results.csv")
    n_cells = len(s.scenarios) * len(s.thresholds) * len(s.seeds) * sum(m == "gcn" for m in s.methods)
    assert len(results[results.method == "gcn"]) == n_cells * 6 * 2          # 6 numbers x 2 protocols
    assert list(results.groupby("protocol").size().index) == ["paper", "siblings"]
    assert "| 0 (no edges) |" in (fig / "table1_recall.md").read_text()
    assert "done: tables and figures in" in smoke_study.stdout


def test_the_direction_report_reads_the_trained_encoders_of_the_smoke_study(smoke_study):
    """direction.md/csv for a study whose variants of gcn change the edges' direction: the gcn rows from the smoke
    study's own cells (trained encoders re-loaded, test graphs embedded again); a variant without cells has no row."""
    import dataclasses

    from monolib.params import Variant
    from monolib.report import direction

    s = load_study("smoke")
    study = dataclasses.replace(s, variants={"gcn_reversed": Variant(gcn={"node_order": "reversed"},
                                                                     ablation_of="gcn", description="reversed")})
    assert direction.methods_of(s) == [] and direction.methods_of(study) == ["gcn", "gcn_reversed"]
    iv = pd.read_csv(paths.figures_dir("smoke") / "intervals.csv")
    table = direction.direction_table(study, iv)
    with_edges = [t for t in s.thresholds if t > 0]
    assert set(table["method"]) == {"gcn"} and len(table) == len(s.scenarios) * len(with_edges)
    assert table["first_share"].between(0, 1).all() and table["uniform_share"].between(0, 0.5).all()
    assert (table["seeds"] == len(s.seeds)).all() and (table["first_label"] >= 1).all()
    recall = iv[(iv.metric == "recall") & (iv.k == 1) & (iv.protocol == "paper") & (iv.method == "gcn")]
    one = table[(table.scenario == "s1") & (table.threshold == 1.0)].iloc[0]
    assert one["recall"] == pytest.approx(recall[(recall.scenario == "s1") & (recall.threshold == 1.0)]["mean"].iloc[0])
    md = direction.direction_markdown(table, {"s1": "GT"})
    assert "Why the direction decides" in md and "s1: GT" in md and "| `gcn` | 1 |" in md


# The smoke study's means on each CPU it has run on, written by tests/refresh_smoke_expected.py. Training on a CPU
# with other vector units (AVX2 / AVX-512, Intel / AMD: other MKL and oneDNN kernels) moves a smoke mean, so the
# notebooks' checked cells print no such number. A row moves by a query or two where it moves (a dataset rendered
# otherwise moved the node-only cell on ground truth by five queries of 24). A band runs from 12.5
# points (three queries) below the lowest machine's mean to 12.5 above the highest, 0.05 for a perception metric:
# a broken pipeline (chance, a constant depth) falls outside.
SMOKE_EXPECTED = yaml.safe_load((paths.ROOT / "tests" / "smoke_expected.yaml").read_text())["machines"]


def smoke_bands(machines: list[dict]) -> tuple[dict, dict]:
    """({(table, scenario, threshold, k): (lo, hi)}, {(model, metric): (lo, hi)}) over every machine's numbers."""
    tables: dict = {}
    perception: dict = {}
    for m in machines:
        for w in m["tables"]:
            key = (w["table"], w["scenario"], str(w["threshold"]), w["k"])
            lo, hi = tables.get(key, (w["mean"], w["mean"]))
            tables[key] = (min(lo, w["mean"]), max(hi, w["mean"]))
        for w in m["perception"]:
            key = (w["model"], w["metric"])
            lo, hi = perception.get(key, (w["value"], w["value"]))
            perception[key] = (min(lo, w["value"]), max(hi, w["value"]))
    return ({k: (lo - 12.5, hi + 12.5) for k, (lo, hi) in tables.items()},
            {k: (lo - 0.05, hi + 0.05) for k, (lo, hi) in perception.items()})


def test_smoke_numbers_within_their_cross_machine_bands(smoke_study):
    """The numbers the notebooks' checked cells do not print (they differ between CPUs), held to the bands of every
    machine the smoke study has run on."""
    fig = paths.figures_dir("smoke")
    tables = {name: pd.read_csv(fig / f"{name}.csv") for name in ("table1_recall", "table2_precision")}
    table_bands, perception_bands = smoke_bands(SMOKE_EXPECTED)
    assert len(table_bands) == 18 and len(perception_bands) == 5
    for (name, scenario, threshold, k), (lo, hi) in table_bands.items():
        t = tables[name]
        row = t[(t.method == "gcn") & (t.scenario == scenario) & (t.threshold == float(threshold)) & (t.k == k)]
        assert len(row) == 1, (name, scenario, threshold, k)
        assert lo <= row["mean"].iloc[0] <= hi, (name, scenario, threshold, k, row["mean"].iloc[0], (lo, hi))
    p = pd.read_csv(fig / "perception.csv")
    for (model, metric), (lo, hi) in perception_bands.items():
        value = p[(p.model == model) & (p.metric == metric)]["value"]
        assert len(value) == 1 and lo <= value.iloc[0] <= hi, (model, metric, list(value), (lo, hi))


def test_the_smoke_bands_span_every_machine_and_this_one_replaces_its_own_entry(tmp_path):
    """A band covers each machine's number and 12.5 points beyond; recording this machine keeps the others' numbers
    and replaces its own (tests/refresh_smoke_expected.py)."""
    import sys

    sys.path.insert(0, str(paths.ROOT / "tests"))
    import refresh_smoke_expected as refresh

    from monolib.device import cpu_signature

    row = {"table": "table1_recall", "scenario": "s1", "threshold": "0", "k": 1}
    machines = [{"cpu": cpu, "tables": [{**row, "mean": mean}],
                 "perception": [{"model": "m", "metric": "x", "value": v}]}
                for cpu, mean, v in [("A", 90.0, 0.5), ("B", 70.0, 0.6)]]
    tables, perception = smoke_bands(machines)
    assert tables[("table1_recall", "s1", "0", 1)] == (57.5, 102.5)
    assert perception[("m", "x")] == pytest.approx((0.45, 0.65))
    fig = tmp_path / "figures"
    fig.mkdir()
    rows = [{"method": "gcn", "scenario": sc, "threshold": th, "k": k, "mean": 50.0}
            for name, keys in refresh.TABLE_ROWS.items() for sc, th, k in keys]
    for name in refresh.TABLE_ROWS:
        pd.DataFrame(rows).to_csv(fig / f"{name}.csv", index=False)
    pd.DataFrame([{"model": m, "metric": x, "value": 0.25} for m, x in refresh.PERCEPTION_ROWS]).to_csv(
        fig / "perception.csv", index=False)
    mine = {"cpu": cpu_signature(), "tables": [], "perception": []}
    out = refresh.recorded(machines + [mine], figures=fig)
    assert [m["cpu"] for m in out] == ["A", "B", cpu_signature()] and out[-1]["tables"][0]["mean"] == 50.0
    assert [m["cpu"] for m in refresh.recorded(machines, only_this_machine=True, figures=fig)] == [cpu_signature()]


def test_every_number_is_recomputed_from_its_rankings(smoke_study):
    """Per protocol, with the protocol enforced: the paper protocol's settings are of different families, the
    siblings protocol's are pairs of one family; every number of results.csv is its cell's rankings recomputed."""
    from monolib.data.protocols import family

    s = load_study("smoke")
    results = pd.read_csv(paths.figures_dir("smoke") / "results.csv")
    files = cell_files("smoke")
    assert files
    shapes = {"paper": s.protocol.settings, "siblings": 2 * s.protocol.siblings}
    checked = 0
    for f in files:
        cell = json.loads(f.read_text())
        rankings = pd.read_csv(f.parent / "rankings.csv")
        protocol = pd.read_csv(f.parent / "protocol.csv")
        check_protocols(rankings, protocol, positives=s.protocol.positives, settings=shapes)
        paper = sorted(protocol[protocol.protocol == "paper"].setting.unique())
        assert len({family(x) for x in paper}) == len(paper) == s.protocol.settings
        assert cell["protocols"]["paper"]["settings"] == paper
        thr = float(cell["threshold"])  # "inf" reads as inf
        for name, r in split_protocols(rankings).items():
            again = recompute_metrics(r, s.protocol.recall_k, s.protocol.precision_k)
            assert again == pytest.approx(cell["metrics"][name], abs=1e-9)
            rows = results[(results.method == cell["method"]) & (results.scenario == cell["scenario"])
                           & (results.threshold == thr) & (results.seed == cell["seed"]) & (results.protocol == name)]
            assert len(rows) == len(again)
            for _, row in rows.iterrows():
                assert row.value == pytest.approx(again[f"{row.metric}@{int(row.k)}"], abs=1e-3)  # csv: 4 decimals
                checked += 1
    assert checked == len(results)


def test_rerun_recomputes_nothing(smoke_study):
    before = {f: f.stat().st_mtime_ns for f in cell_files("smoke")}
    out = subprocess.run(MONOLIB + ["study", "smoke"], env=ENV, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "0 to run" in out.stdout
    assert "nothing to do" in out.stdout + out.stderr  # perception cached
    assert {f: f.stat().st_mtime_ns for f in cell_files("smoke")} == before


def test_perception_command_is_cached_and_draws_its_figures(smoke_study):
    fig = paths.figures_dir("smoke")
    for name in ("perception_training.png", "fig3_depth.png", "fig4_semantics.png"):
        (fig / name).unlink(missing_ok=True)
    out = subprocess.run(MONOLIB + ["perception", "smoke"], env=ENV, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count("nothing to do") == 3  # the segmentation net and both depth nets
    assert "pixel_accuracy" in out.stdout and "delta1" in out.stdout
    for name in ("perception_training.png", "fig3_depth.png", "fig4_semantics.png"):
        assert (fig / name).stat().st_size > 10_000, name


def test_cells_with_the_graphs_of_a_smaller_threshold_are_exact_copies(smoke_study, tmp_path):
    """The runner copies a cell whose graphs equal a smaller threshold's; running it for real gives the same."""
    from monolib.graphs import scenegraphs
    from monolib.graphs.build import at_threshold
    from monolib.retrieval import cell
    from monolib.study.copies import same_graphs
    from monolib.study.runner import CellSpec, grid

    s = load_study("smoke")
    copied = [json.loads(f.read_text()) for f in cell_files("smoke")]
    copied = [c for c in copied if c.get("same_graphs_as")]
    assert copied, "the smoke study has thresholds with identical graphs (predicted depth: all pairs within 5 m)"
    c = max(copied, key=lambda c: (c["scenario"], str(c["threshold"])))
    thr = float(c["threshold"])  # "inf" reads as inf
    source_thr = same_graphs(s, grid(s))[CellSpec(c["method"], c["scenario"], thr, c["seed"]).name].threshold
    for split in scenegraphs.load(s, c["scenario"]).values():
        for g in split:
            assert at_threshold(g, thr).edge_index.tolist() == at_threshold(g, source_thr).edge_index.tolist()
    again = cell.run_cell(s, c["method"], c["scenario"], thr, c["seed"], out_dir=str(tmp_path / "again"))
    assert again["metrics"] == c["metrics"]
    folder = paths.cell_dir("smoke", c["method"], c["scenario"], thr, c["seed"])
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "again" / "rankings.csv"),
                                  pd.read_csv(folder / "rankings.csv"))


def test_cells_reading_the_inputs_of_another_scenario_are_exact_copies(smoke_study, tmp_path):
    """A scenario whose encoder inputs equal an earlier scenario's (here a twin of s4: the same sources) is copied
    from it cell by cell; running the copy for real gives the same files. Scenarios with other semantics are not."""
    from monolib.retrieval import cell
    from monolib.study.copies import same_graphs
    from monolib.study.runner import CellSpec, grid

    data = {"name": "smoke_twin", "extends": "smoke", "thresholds": [0, 1], "seeds": [0],
            "scenarios": {"s4_twin": {"depth": "depth_b", "semantic": "deeplab", "label": "s4 again"}}}
    study_file = tmp_path / "smoke_twin.yaml"
    study_file.write_text(yaml.safe_dump(data))
    s = load_study(study_file)
    copies = same_graphs(s, grid(s))
    twin = CellSpec("gcn", "s4_twin", 0.0, 0).name
    assert copies[twin].scenario == "s4" and copies[twin].threshold == 0.0
    assert CellSpec("gcn", "s2", 0.0, 0).name not in copies  # GT depth, DeepLab: not the inputs of s1 (GT semantics)
    a = cell.run_cell(s, "gcn", "s4", 0.0, 0, out_dir=str(tmp_path / "s4"))
    b = cell.run_cell(s, "gcn", "s4_twin", 0.0, 0, out_dir=str(tmp_path / "twin"))
    assert a["metrics"] == b["metrics"]
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "s4" / "rankings.csv"),
                                  pd.read_csv(tmp_path / "twin" / "rankings.csv"))
    record = cell.copy_cell(tmp_path / "s4", tmp_path / "copy", 0.0, "gcn/s4__t0__s0", "KEY",
                            cell.scenario_fields(s, "s4_twin"))
    assert (record["scenario"], record["scenario_label"], record["same_inputs_as"]) == ("s4_twin", "s4 again",
                                                                                        "gcn/s4__t0__s0")
    assert "same_graphs_as" not in record and record["metrics"] == a["metrics"]


def test_killed_study_resumes_without_recomputing(smoke_study, tmp_path):
    """A study over the smoke dataset (ground truth only): killed after its first cells, then run again."""
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data.update(name="smoke_resume", thresholds=[1, 2], seeds=[0, 1], jobs=1,
                scenarios={"s1": data["scenarios"]["s1"]})
    data["dataset"]["root"] = str(load_study("smoke").dataset_root)
    study_file = tmp_path / "smoke_resume.yaml"
    study_file.write_text(yaml.safe_dump(data))
    study_dir = paths.study_dir("smoke_resume")
    subprocess.run(["rm", "-rf", str(study_dir)], check=True)
    proc = subprocess.Popen(MONOLIB + ["study", str(study_file)], env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 600
    while len(cell_files("smoke_resume")) < 2 and time.time() < deadline and proc.poll() is None:
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    done = {f: f.stat().st_mtime_ns for f in cell_files("smoke_resume")}
    assert 2 <= len(done) < 4
    for f in done:  # a kill never leaves a half-written result under its final name
        assert json.loads(f.read_text())["metrics"]
    out = subprocess.run(MONOLIB + ["study", str(study_file)], env=ENV, capture_output=True, text=True, timeout=1200)
    assert out.returncode == 0, out.stderr[-3000:]
    assert f"{len(done)} already complete" in out.stdout
    after = {f: f.stat().st_mtime_ns for f in cell_files("smoke_resume")}
    assert len(after) == 4
    assert all(after[f] == t for f, t in done.items())


def test_papermill_cell_with_unlisted_threshold_and_seed(smoke_study, tmp_path, monkeypatch):
    """papermill as a user calls it, from another directory, with a threshold and seed no study lists."""
    out = tmp_path / "cell"
    monkeypatch.chdir(tmp_path)
    papermill.execute_notebook(str(paths.NOTEBOOKS / "ablation_cell.ipynb"), str(tmp_path / "out.ipynb"),
                               parameters={"study": "smoke", "scenario": "s2", "threshold": 3.7, "seed": 11,
                                           "out_dir": str(out)}, kernel_name="python3", progress_bar=False)
    cell = json.loads((out / "cell.json").read_text())
    assert cell["threshold"] == 3.7 and cell["seed"] == 11 and cell["method"] == "gcn"
    rankings = pd.read_csv(out / "rankings.csv")
    assert list(rankings.columns) == ["protocol", "query", "query_setting", "rank", "match", "match_setting",
                                      "distance"]
    s = load_study("smoke")
    n_settings = s.protocol.settings + 2 * s.protocol.siblings
    assert rankings["rank"].max() == 10 and len(rankings) == 10 * n_settings * s.protocol.queries
    for name, r in split_protocols(rankings).items():
        assert recompute_metrics(r, [1, 5, 10], [2, 4, 6]) == pytest.approx(cell["metrics"][name])
    # same study, scenario, threshold and seed: the same numbers (determinism)
    from monolib.retrieval.cell import run_cell

    again = run_cell(s, "gcn", "s2", 3.7, 11, out_dir=str(tmp_path / "again"))
    for name in ("paper", "siblings"):
        assert again["metrics"][name] == pytest.approx(cell["metrics"][name])
    # infinity passes through papermill too
    papermill.execute_notebook(str(paths.NOTEBOOKS / "ablation_cell.ipynb"), str(tmp_path / "inf.ipynb"),
                               parameters={"threshold": math.inf, "seed": 11, "out_dir": str(tmp_path / "inf")},
                               kernel_name="python3", progress_bar=False)
    assert json.loads((tmp_path / "inf" / "cell.json").read_text())["threshold"] == "inf"


def test_the_layout_encoder_localizes_a_frame_of_its_database(smoke_study, tmp_path):
    """quick's `layout` encoder (pair readout, nodes without message passing, batch-hard over families) trained as a
    cell of the smoke study's data (s3: predicted depth and semantics, every pair an edge): the localizer rebuilds
    the cell's test embeddings from the cached graphs, and the RGB of one of its frames, through perception, the
    graph and the encoder, finds that frame first."""
    import cv2
    import torch

    from monolib import localize
    from monolib.data import dataset, selection
    from monolib.graphs import scenegraphs
    from monolib.retrieval import gcn
    from monolib.retrieval.cell import run_cell

    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["variants"] = {"layout": {"gcn": yaml.safe_load((paths.PARAMS / "quick.yaml").read_text())["variants"]
                                   ["layout"]["gcn"], "thresholds": [math.inf], "scenarios": ["s3"]}}
    study_path = tmp_path / "smoke_layout.yaml"
    study_path.write_text(yaml.safe_dump(data, sort_keys=False))
    s = load_study(study_path)
    cell = tmp_path / "cell"
    record = run_cell(s, "layout", "s3", math.inf, 0, out_dir=str(cell))
    assert record["encoder"]["pair_readout"] and not record["encoder"]["message_passing"]
    spec = s.gcn_spec("layout")
    model = gcn.GraphEncoder(spec)
    model.load_state_dict(torch.load(cell / "model.pt", weights_only=True))
    test = [gcn.encoder_graph(g, math.inf, spec, s.projection("s3")) for g in scenegraphs.load(s, "s3")["test"]]
    emb = gcn.embed(model, test).numpy()
    np.testing.assert_array_equal(emb, np.load(cell / "embeddings.npy"))
    db = localize.write_database(tmp_path / "db", s, {**record, "folder": str(cell)}, model.state_dict(),
                                 [g.frame for g in test], [g.setting for g in test], emb)
    frame = selection.select_frames(s, dataset.open_dataset(s), s.gcn.val_settings).test[3]
    same = tmp_path / "same.png"
    cv2.imwrite(str(same), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    first, second = localize.localize([str(same)], db, k=3)[0]["matches"][:2]
    assert first["image"] == frame.key and first["place"] == frame.setting, first
    assert first["distance"] < 0.5 * second["distance"], (first, second)


def test_index_and_localize_images_it_never_saw(smoke_study, tmp_path, capsys, monkeypatch):
    import cv2

    from monolib.data import dataset, selection

    db = tmp_path / "db"
    out = subprocess.run(MONOLIB + ["index", "smoke", "--out", str(db)], env=ENV, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    s = load_study("smoke")
    ds = dataset.open_dataset(s)
    frame = selection.select_frames(s, ds, s.gcn.val_settings).test[5]
    png, jpg = tmp_path / "query.png", tmp_path / "query.jpg"
    cv2.imwrite(str(png), cv2.cvtColor(cv2.resize(frame.rgb, (500, 400)), cv2.COLOR_RGB2BGR))  # another size and aspect
    cv2.imwrite(str(jpg), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    # localize through the command's own entry point in this process (the index above ran as its own process)
    from monolib import cli

    capsys.readouterr()
    assert cli.main(["localize", str(png), str(jpg), "--db", str(db), "--k", "3", "--json"]) == 0
    results = json.loads(capsys.readouterr().out)
    assert [len(r["matches"]) for r in results] == [3, 3]
    settings = {g.setting for g in selection.select_frames(s, ds, s.gcn.val_settings).test}
    for r in results:
        assert [m["rank"] for m in r["matches"]] == [1, 2, 3]
        assert all(m["place"] in settings for m in r["matches"])
        assert len({m["place"] for m in r["matches"]}) == 3
        assert all(a["distance"] <= b["distance"] for a, b in zip(r["matches"], r["matches"][1:]))
    # the RGB of a frame of the database, lossless at its own size: that frame comes first, far ahead of the next
    # (a localizer that ranked anything but the query's own scene graph first would fail here)
    same = tmp_path / "same.png"
    cv2.imwrite(str(same), cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR))
    assert cli.main(["localize", str(same), "--db", str(db), "--k", "3", "--json"]) == 0
    first, second = json.loads(capsys.readouterr().out)[0]["matches"][:2]
    assert first["image"] == frame.key and first["place"] == frame.setting, first
    assert first["distance"] < 0.5 * second["distance"], (first, second)
    # the printed table and one clear error each (a wrong path, an unreadable image, a database made by other
    # models)
    assert cli.main(["localize", str(png), "--db", str(db)]) == 0 and "1. ai_" in capsys.readouterr().out
    monkeypatch.chdir(tmp_path)
    bad = tmp_path / "broken.jpg"
    bad.write_bytes(b"not an image")
    for args, message in ((["nope.png"], "nope.png: image file not found"),
                          ([str(bad)], "broken.jpg: not a readable image")):
        assert cli.main(["localize", *args, "--db", str(db)]) == 2
        err = capsys.readouterr().err
        assert message in err, err[-2000:]
    meta = json.loads((db / "meta.json").read_text())
    meta["files"]["depth.pt"] = "0" * 64
    (db / "meta.json").write_text(json.dumps(meta))
    assert cli.main(["localize", str(png), "--db", str(db)]) == 2
    assert "made by other models than those it holds" in capsys.readouterr().err


def test_changing_only_a_gcn_parameter_redoes_no_perception(smoke_study, tmp_path, capsys):
    from monolib.graphs import scenegraphs
    from monolib.perception import predictions

    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["gcn"].update(epochs=data["gcn"]["epochs"] + 7, lr=0.01)
    p = tmp_path / "smoke.yaml"
    p.write_text(yaml.safe_dump(data))
    s = load_study(p)
    table = predictions.run(s, progress=False)
    assert set(table.attrs["status"].values()) == {"cached"}
    assert "nothing to do" in capsys.readouterr().out
    # the scene graphs do not depend on the GCN either
    assert all(scenegraphs.graphs_path(s, sc) == scenegraphs.graphs_path(load_study("smoke"), sc) for sc in s.scenarios)


def test_threshold_zero_gives_graphs_without_edges_and_cells_that_run(smoke_study):
    from monolib.graphs import scenegraphs
    from monolib.graphs.build import at_threshold
    from monolib.study.copies import same_graphs
    from monolib.study.runner import grid

    s = load_study("smoke")
    assert s.thresholds[0] == 0.0
    zero = [json.loads(f.read_text()) for f in cell_files("smoke")]
    zero = [c for c in zero if float(c["threshold"]) == 0.0]
    assert sorted(c["scenario"] for c in zero) == sorted(s.scenarios)
    for c in zero:
        assert c["test_edges_mean"] == 0.0 and c["test_nodes_mean"] > 0 and not c.get("same_graphs_as")
        assert set(c["metrics"]) == {"paper", "siblings"}
        assert 0.0 <= c["metrics"]["paper"]["recall@1"] <= 100.0
        assert (paths.cell_dir("smoke", "gcn", c["scenario"], 0, 0) / "model.pt").is_file()
    for split in scenegraphs.load(s, "s1").values():
        for g in split:
            assert at_threshold(g, 0.0).edge_index.shape[1] == 0 and at_threshold(g, 0.0).num_nodes == g.num_nodes
    # a copied cell's source has the same graphs: never 0 unless the copy has no edge either
    sizes = pd.read_csv(paths.figures_dir("smoke") / "graph_sizes.csv", dtype={"threshold": str})
    for name, source in same_graphs(s, grid(s)).items():
        scenario, thr = name.split("/")[1].split("__t")[0], name.split("__t")[1].split("__")[0]
        if source.threshold == 0.0:
            row = sizes[(sizes.scenario == scenario) & (sizes.threshold == thr)].iloc[0]
            assert row["test_edges"] == 0 and row["train_edges"] == 0


def test_graph_sizes_table_of_the_smoke_study(smoke_study):
    """graph_sizes.csv: every scenario x threshold of the grid; nodes do not depend on the threshold, edges grow
    with it (0 at 0, every pair at inf), the means are those of the cached graphs, and `same_graphs_as` is the
    runner's rule (`monolib.study.copies.same_graphs`)."""
    from monolib.graphs import scenegraphs
    from monolib.study.copies import same_graphs
    from monolib.study.runner import grid

    s = load_study("smoke")
    fig = paths.figures_dir("smoke")
    sizes = pd.read_csv(fig / "graph_sizes.csv", dtype={"threshold": str, "same_graphs_as": str}, keep_default_na=False)
    assert list(sizes.columns) == graph_sizes.SIZE_COLUMNS
    assert len(sizes) == len(s.scenarios) * len(s.thresholds)
    assert list(sizes[sizes.scenario == "s1"]["threshold"]) == [paths.threshold_tag(t) for t in s.thresholds]
    copies = same_graphs(s, grid(s))
    for sc, g in sizes.groupby("scenario", sort=False):
        graphs = scenegraphs.load(s, sc)
        test, train = graphs["test"], graphs["train"] + graphs["val"]
        assert g["test_graphs"].tolist() == [len(test)] * len(g) and g["train_graphs"].tolist() == [len(train)] * len(g)
        assert g["test_nodes"].iloc[0] == pytest.approx(np.mean([x.num_nodes for x in test]), rel=1e-3)
        assert g["train_nodes"].nunique() == 1 and g["test_nodes"].nunique() == 1
        assert g["test_edges"].iloc[0] == 0 and g["train_edges"].iloc[0] == 0          # threshold 0: no edges
        assert (np.diff(g["test_edges"]) >= 0).all() and (np.diff(g["train_edges"]) >= 0).all()
        pairs = np.mean([x.num_nodes * (x.num_nodes - 1) / 2 for x in test])
        assert g["test_edges"].iloc[-1] == pytest.approx(pairs, rel=1e-3)              # inf: every pair
        for t, same in zip(g["threshold"], g["same_graphs_as"]):
            name = f"gcn/{sc}__t{t}__s0"
            assert same == (paths.threshold_tag(copies[name].threshold) if name in copies else ""), name
    md = (fig / "graph_sizes.md").read_text()
    assert md.startswith("**Graph sizes.**") and "| 0 (no edges) |" in md


def test_smoke_study_perception_rerun_is_cached(smoke_study, capsys):
    """predictions.run on the real smoke study, twice: the second run trains and predicts nothing."""
    from monolib.perception import predictions

    study = load_study("smoke")
    predictions.run(study, progress=False)
    capsys.readouterr()
    again = predictions.run(study, progress=False)
    out = capsys.readouterr().out
    assert set(again.attrs["status"].values()) == {"cached"}
    assert f"perception: {predictions.model_tag(study, 'deeplab')} cached" in out and "nothing to do" in out
