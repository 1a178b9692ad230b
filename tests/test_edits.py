"""Edits of built scene graphs, one property of the data each (`monolib.graphs.edits`), and the data-edits study's
file and tables (`monolib.study.data_edits`)."""
import math

import numpy as np
import pandas as pd
import pytest
import torch

from monolib.graphs import build, edits
from monolib.params import StudyError
from monolib.report import data_edits as tables
from monolib.study import data_edits

WALL, FLOOR, WINDOW, LAMP = 1, 2, 9, 35


def graph(labels, colours, setting="ai_001_001", frame=None):
    """A complete graph of nodes with these NYU40 ids and grey levels, on a line 1 m apart."""
    x = [[lab, c, c, c] for lab, c in zip(labels, colours)]
    pos = [[float(i), 0.0, 2.0] for i in range(len(labels))]
    return build.complete_graph(x, pos, setting, frame or f"{setting}/cam_00/{id(x)}")


def test_light_ratios_and_relight_move_one_label_to_the_target():
    graphs = [graph([WALL, FLOOR, LAMP], [0.2, 0.3, 2.8]), graph([WALL, LAMP], [0.2, 2.8])]
    ratios = edits.light_ratios(graphs)
    assert ratios[WALL] == 1.0 and ratios[LAMP] == pytest.approx(14.0) and ratios[FLOOR] == pytest.approx(1.5)
    factors = edits.light_factors(ratios, {WALL: 1.0, LAMP: 1.4, 40: 2.0})
    assert set(factors) == {WALL, LAMP} and factors[LAMP] == pytest.approx(0.1)  # floor: no target, kept
    out = edits.relight(graphs, factors)
    assert edits.light_ratios(out)[LAMP] == pytest.approx(1.4)
    assert torch.equal(out[0].x[:2], graphs[0].x[:2])                      # the other labels keep their colours
    assert graphs[0].x[2, 1].item() == pytest.approx(2.8)                  # the inputs are not changed
    assert torch.equal(out[0].pair_len, graphs[0].pair_len)


def test_keep_nodes_keeps_the_pairs_between_the_kept_nodes_with_their_lengths():
    g = graph([WALL, FLOOR, WINDOW, LAMP], [0.1, 0.2, 0.3, 0.4])
    out = edits.keep_nodes(g, torch.tensor([True, False, True, True]))
    assert out.num_nodes == 3 and out.x[:, 0].tolist() == [WALL, WINDOW, LAMP]
    pairs = {tuple(p): length for p, length in zip(out.pair_index.T.tolist(), out.pair_len.tolist())}
    assert pairs == {(0, 1): 2.0, (0, 2): 3.0, (1, 2): 1.0}                # nodes 0, 2, 3 of a line 1 m apart
    at = build.at_threshold(out, 2.5)
    assert at.edge_index.shape[1] == 4                                      # pairs under 2.5 m, both directions


def test_thin_label_keeps_the_share_asked_for_drawn_per_frame():
    graphs = [graph([WALL, WINDOW], [0.2, 0.5], setting=f"ai_001_{i // 10:03d}", frame=f"f{i}") for i in range(400)]
    assert edits.label_share(graphs, WINDOW) == 1.0
    thinned = edits.thin_label(graphs, WINDOW, 0.4, seed=0)
    assert 0.33 < edits.label_share(thinned, WINDOW) < 0.47
    assert all(g.x[0, 0] == WALL for g in thinned)                          # only the window goes
    again = edits.thin_label(list(reversed(graphs)), WINDOW, 0.4, seed=0)[::-1]
    assert [g.num_nodes for g in again] == [g.num_nodes for g in thinned]   # the same draw in any order
    other = edits.thin_label(graphs, WINDOW, 0.4, seed=1)
    assert [g.num_nodes for g in other] != [g.num_nodes for g in thinned]
    assert edits.label_share(edits.thin_label(graphs, WINDOW, 0.0, 0), WINDOW) == 0.0
    with pytest.raises(ValueError, match="share 1.5"):
        edits.thin_label(graphs, WINDOW, 1.5, 0)


def test_drop_nodes_keeps_walls_and_floors():
    graphs = [graph([WALL, FLOOR, 5, 7, 40], [0.2] * 5, frame=f"f{i}") for i in range(50)]
    out = edits.drop_nodes(graphs, 0.5, seed=0)
    assert all({WALL, FLOOR} <= set(g.x[:, 0].long().tolist()) for g in out)
    assert 2.8 < np.mean([g.num_nodes for g in out]) < 4.2


def test_the_settings_light_levels_spread_as_asked_and_the_labels_keep_theirs():
    rng = np.random.default_rng(0)
    graphs = []
    for s in range(12):
        level = rng.normal(0, 0.8)
        for f in range(5):
            graphs.append(graph([WALL, FLOOR, LAMP], np.exp(level + np.array([0.0, 0.4, 2.0]) + rng.normal(0, .1, 3)),
                                setting=f"ai_{s:03d}_001", frame=f"s{s}f{f}"))
    setting, label = edits.light_effects(graphs)
    sd = np.std(list(setting.values()))
    assert 0.3 < sd and abs(np.mean(list(setting.values()))) < 1e-9
    assert label[LAMP] - label[WALL] == pytest.approx(2.0, abs=0.1)
    wider = edits.light_effects(edits.spread_setting_light(graphs, 2.0))
    assert np.std(list(wider[0].values())) == pytest.approx(2 * sd, rel=1e-6)
    assert wider[1][LAMP] - wider[1][WALL] == pytest.approx(label[LAMP] - label[WALL], abs=1e-6)
    flat = edits.light_effects(edits.spread_setting_light(graphs, 0.0))
    assert np.std(list(flat[0].values())) < 1e-6


def write(tmp_path, text):
    path = tmp_path / "edits.yaml"
    path.write_text(text)
    return path


GOOD = """name: t
legs: {a: {study: smoke}, b: {study: smoke, folds: [0]}}
scenario: s1
methods: [gcn]
thresholds: [5]
seeds: [0]
edits: [none, setting_light]
"""


@pytest.mark.parametrize("change, message", [
    (("seeds: [0]", "seeds: [0]\ncolour: red"), r"unknown keys \['colour'\]"),
    (("edits: [none, setting_light]", "edits: [none, brighter]"), r"edits: \['brighter'\]: expected some of"),
    (("edits: [none, setting_light]", "edits: [setting_light]"), "`none` among them"),
    (("legs: {a: {study: smoke}, b: {study: smoke, folds: [0]}}", "legs: {a: {study: smoke}}"), "two legs"),
    (("thresholds: [5]", "thresholds: [0]"), "expected distances > 0"),
    (("seeds: [0]\n", ""), r"missing keys \['seeds'\]"),
])
def test_a_bad_data_edits_file_is_one_error_naming_the_file_and_key(tmp_path, change, message):
    path = write(tmp_path, GOOD.replace(*change))
    with pytest.raises(StudyError, match=message) as err:
        data_edits.load(path)
    assert str(path) in str(err.value)


def test_the_good_file_loads(tmp_path):
    es = data_edits.load(write(tmp_path, GOOD))
    assert es.legs["b"].folds == [0] and es.legs["a"].folds is None and es.thresholds == [5.0]


def record(leg, edit, method, threshold, seed, hits):
    settings = [f"s{i // 4}" for i in range(len(hits))]
    return {"leg": leg, "edit": edit, "method": method, "threshold": threshold, "seed": seed, "fold": None,
            "hits": hits, "query_settings": settings, "recall@1": 100.0 * np.mean(hits)}


def test_the_penalty_and_the_edits_change_are_paired_differences(tmp_path):
    es = data_edits.load(write(tmp_path, GOOD.replace("folds: [0]", "folds: null")))
    rows = []
    for leg in ("a", "b"):
        for seed in (0,):
            base0 = [1] * 12 + [0] * 4            # 75 without edges
            rows += [record(leg, "none", "gcn", 0.0, seed, base0),
                     record(leg, "none", "gcn", 5.0, seed, [1] * 4 + [0] * 12),          # 25: penalty -50
                     record(leg, "setting_light", "gcn", 0.0, seed, base0),
                     record(leg, "setting_light", "gcn", 5.0, seed, [1] * 8 + [0] * 8)]  # 50: penalty -25
    table = tables.penalty_table(pd.DataFrame(rows), es)
    row = table[(table.leg == "a") & (table.edit == "setting_light")].iloc[0]
    assert row.recall_no_edges == 75.0 and row.penalty == -25.0 and row.change == 25.0
    none = table[(table.leg == "a") & (table.edit == "none")].iloc[0]
    assert none.penalty == -50.0 and none.change == 0.0 and none.change_lo == none.change_hi == 0.0
    assert row.penalty_lo <= row.penalty <= row.penalty_hi and not math.isnan(row.change_lo)


def test_the_command_says_error_and_exits_2_on_a_bad_file_or_leg(tmp_path, capsys):
    from monolib import cli

    bad = write(tmp_path, GOOD.replace("seeds: [0]", "seeds: [0]\nlight: on"))
    assert cli.main(["data-edits", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(bad) in err and "unknown keys ['light']" in err and err.count("\n") == 1
    assert cli.main(["data-edits", str(write(tmp_path, GOOD)), "--leg", "c"]) == 2
    assert "leg 'c': not in legs (a, b)" in capsys.readouterr().err
    assert cli.main(["data-edits", str(write(tmp_path, GOOD))]) == 2  # smoke is not split by volume
    assert "legs.b.folds: [0], but" in capsys.readouterr().err
