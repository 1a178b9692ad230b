"""Node colours in the two spaces of `graphs.colour`, through the graph stage on Hypersim-layout files: HDR medians
against medians computed by hand from color.hdf5, tonemapped colours as the tonemapped frame gives them, the key
of each space in the caches, a missing color.hdf5, and the localizer's refusal of HDR colours."""
import numpy as np
import pytest
import yaml
from hypersim_files import write_setting

from monolib import cli, paths
from monolib.data.hypersim import HdrMissing, HypersimDataset, tonemap
from monolib.graphs import scenegraphs
from monolib.graphs.build import grouped_median_u8
from monolib.io import read_h5, write_h5
from monolib.params import StudyError, load_study

SETTINGS = ["ai_001_001", "ai_002_001", "ai_001_002", "ai_002_002", "ai_003_001", "ai_003_002"]


@pytest.fixture
def dataset(tmp_path, monkeypatch):
    """Six settings of two frames, each frame's color.hdf5 random per pixel (float16 HDR radiance, 0.001-5)."""
    root = tmp_path / "data"
    rng = np.random.default_rng(39)
    for i, setting in enumerate(SETTINGS):
        write_setting(root, setting, frames=2, split="test" if i < 2 else "train")
        for f in (root / setting / "images" / "scene_cam_00_final_hdf5").glob("*.color.hdf5"):
            write_h5(f, rng.uniform(1e-3, 5.0, (48, 64, 3)).astype(np.float16))
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    return root


def study(tmp_path, root, colour="hdr", scenario_colour=None):
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    s1 = {"depth": "gt", "semantic": "gt", **({"colour": scenario_colour} if scenario_colour else {})}
    data.update(name="colour_test", scenarios={"s1": s1})
    data["graphs"]["colour"] = colour
    data["dataset"].update(source="hypersim", root=str(root), workers=1)
    data["protocol"].update(settings=2, siblings=0, frames=2, queries=1, positives=1)
    data["gcn"].update(val_settings=1)
    p = tmp_path / f"study_{colour}_{scenario_colour}.yaml"
    p.write_text(yaml.safe_dump(data))
    return load_study(p)


def hand_medians(root, frame_key):
    """{label: (R, G, B)}: per label, np.median of color.hdf5 over its pixels with a label >= 1 and valid depth."""
    f = HypersimDataset(root).frame_by_key(frame_key)
    color = read_h5(f.files["color"]).astype(np.float64)
    semantic, depth = f.semantic, f.depth_meters
    valid = (semantic >= 1) & np.isfinite(depth) & (depth > 0)
    return {int(lab): np.median(color[valid & (semantic == lab)], axis=0) for lab in np.unique(semantic[valid])}


def test_hdr_node_colours_are_the_medians_of_color_hdf5(tmp_path, dataset):
    graphs = scenegraphs.load(study(tmp_path, dataset, "hdr"), "s1")
    for g in graphs["train"][:3] + graphs["test"][:2]:
        want = hand_medians(dataset, g.frame)
        assert sorted(want) == g.x[:, 0].long().tolist()
        for row in g.x:
            assert row[1:].numpy() == pytest.approx(want[int(row[0])].astype(np.float32), rel=0, abs=0)
        assert float(g.x[:, 1:].max()) > 1.0  # radiance, not a 0..1 tonemapped colour


def test_tonemapped_node_colours_are_those_of_the_tonemapped_frame(tmp_path, dataset):
    """`tonemapped` takes each node's colour as the stage always took it: the exact median of the frame's
    tonemapped uint8 RGB (Hypersim's tonemap over the pixels with a render entity), divided by 255."""
    graphs = scenegraphs.load(study(tmp_path, dataset, "tonemapped"), "s1")
    ds = HypersimDataset(dataset)
    for g in graphs["train"][:3]:
        f = ds.frame_by_key(g.frame)
        rgb = tonemap(read_h5(f.files["color"]), read_h5(f.files["render_entity_id"]) != -1)
        valid = ((f.semantic >= 1) & np.isfinite(f.depth_meters) & (f.depth_meters > 0)).reshape(-1)
        labels = f.semantic.reshape(-1)[valid]
        uniq = np.unique(labels)
        want = (grouped_median_u8(labels, rgb.reshape(-1, 3)[valid], uniq) / 255.0).astype(np.float32)
        assert np.array_equal(g.x[:, 1:].numpy(), want)
        assert float(g.x[:, 1:].max()) <= 1.0


def test_each_colour_space_has_its_own_graphs_file(tmp_path, dataset):
    """The space is part of the graph key: graphs built in one are never read for the other, and a scenario's own
    `colour` overrides the study's."""
    hdr, tm = study(tmp_path, dataset, "hdr"), study(tmp_path, dataset, "tonemapped")
    assert scenegraphs.scenario_key(hdr, "s1") != scenegraphs.scenario_key(tm, "s1")
    assert scenegraphs.scenario_key(study(tmp_path, dataset, "hdr", "tonemapped"), "s1") == \
        scenegraphs.scenario_key(tm, "s1")
    a, b = scenegraphs.load(hdr, "s1"), scenegraphs.load(tm, "s1")
    assert scenegraphs.graphs_path(hdr, "s1").is_file() and scenegraphs.graphs_path(tm, "s1").is_file()
    assert not np.array_equal(a["train"][0].x[:, 1:].numpy(), b["train"][0].x[:, 1:].numpy())
    assert np.array_equal(a["train"][0].x[:, 0].numpy(), b["train"][0].x[:, 0].numpy())  # same nodes
    assert np.array_equal(a["train"][0].pos.numpy(), b["train"][0].pos.numpy())


def test_a_frame_without_color_hdf5_is_one_error_naming_it_for_hdr(tmp_path, dataset):
    missing = dataset / "ai_003_001" / "images" / "scene_cam_00_final_hdf5" / "frame.0001.color.hdf5"
    missing.unlink()
    with pytest.raises(HdrMissing, match=f"^{missing}: file not found; node colours of `graphs.colour: hdr`"):
        scenegraphs.load(study(tmp_path, dataset, "hdr"), "s1")
    tm = scenegraphs.load(study(tmp_path, dataset, "tonemapped"), "s1")  # tonemapped: a black frame, as always
    g = next(g for g in tm["train"] if g.frame == "ai_003_001/cam_00/0001")
    assert g.num_nodes == 2 and float(g.x[:, 1:].abs().sum()) == 0.0


@pytest.mark.parametrize("where, value, message", [
    ("graphs", "linear", "graphs.colour: expected one of hdr, tonemapped, got 'linear'"),
    ("scenario", "srgb", "scenarios.s1.colour: expected one of hdr, tonemapped, got 'srgb'"),
])
def test_an_unknown_colour_space_is_refused(tmp_path, where, value, message):
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    if where == "graphs":
        data["graphs"]["colour"] = value
    else:
        data["scenarios"]["s1"]["colour"] = value
    p = tmp_path / "s.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(StudyError, match=message):
        load_study(p)


def test_published_graphs_are_hdr_only(tmp_path):
    data = yaml.safe_load((paths.PARAMS / "published.yaml").read_text())
    data["graphs_root"] = str(tmp_path)
    data["graphs"]["colour"] = "tonemapped"
    p = tmp_path / "p.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(StudyError, match="graphs.colour: published graphs hold medians of the HDR color.hdf5"):
        load_study(p)


def test_the_localizer_refuses_a_graph_cell_of_hdr_colours(tmp_path, monkeypatch, capsys):
    """A photo has no HDR radiance: the localizer never encodes with a cell of HDR node colours. Asked not to train
    (`train=False`), picking a cell of a study whose predicted-input scenarios take HDR colours is one error naming
    the key (`monolib index` trains the cell's tonemapped twin instead: tests/test_localize_places.py); a database
    that says it holds HDR colours is refused by `localize`."""
    import json

    from monolib import localize
    from monolib.retrieval.gcn import GraphEncoder

    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["scenarios"]["s3"].pop("colour", None)  # every scenario hdr
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(data))
    s = load_study(p)
    cell = tmp_path / "runs" / "smoke" / "cells" / "gcn" / "s3__t1__s0"
    cell.mkdir(parents=True)
    (cell / "cell.json").write_text(json.dumps({"method": "gcn", "scenario": "s3", "threshold": 1.0, "seed": 0,
                                                "metrics": {"paper": {"recall@1": 0.5}}}))
    (cell / "model.pt").write_bytes(b"")
    with pytest.raises(localize.LocalizeError, match="graphs.colour: hdr: the encoders of this study's graph cells"):
        localize.pick_cell(s, train=False)
    assert localize.pick_cell(load_study("smoke"))["scenario"] == "s3"  # smoke's s3 is tonemapped
    db = localize.write_database(tmp_path / "db", s, {**json.loads((cell / "cell.json").read_text()),
                                                      "folder": str(cell)}, GraphEncoder(s.gcn_spec("gcn")),
                                 ["ai_001_001/cam_00/0000"], ["ai_001_001"], np.zeros((1, 64), np.float32),
                                 perception_files={"semantic": ("deeplab", cell / "model.pt"),
                                                   "depth": ("depth_a", cell / "model.pt")})
    assert json.loads((db / "meta.json").read_text())["colour"] == "hdr"
    code = cli.main(["localize", str(tmp_path / "missing.png"), "--db", str(db)])
    err = capsys.readouterr().err
    assert code == 2 and "node colours 'hdr'" not in err and "graphs.colour: hdr" in err, err
