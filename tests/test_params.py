"""Study files: the committed ones load; bad ones fail with one error naming the key."""
import dataclasses
import math
import os

import pytest
import yaml

from monolib import paths, study_file_doc
from monolib.params import (DatasetSpec, DepthSpec, GCNSpec, GraphsSpec, MoreSeeds, PerceptionSpec, Protocol,
                            Scenario, SegmentationSpec, Study, StudyError, Variant, load_study, resolve_path,
                            study_keys)


def _merged(base: dict, over: dict) -> dict:
    """What `extends:` means, written out again here: mappings merged key by key, anything else replaced, a mapping
    set to null removed."""
    out = dict(base)
    for k, v in over.items():
        if v is None and isinstance(base.get(k), dict):
            del out[k]
        else:
            out[k] = _merged(base[k], v) if isinstance(v, dict) and isinstance(base.get(k), dict) else v
    return out


def _assert_loaded(loaded, raw, where: str) -> None:
    """Every value the YAML gives is the loaded study's value at the same key (dataclass fields, mapping keys and
    list items alike), numbers compared as numbers (thresholds read as floats, `.inf` as infinity)."""
    if isinstance(raw, dict):
        for k, v in raw.items():
            if isinstance(loaded, dict):
                assert k in loaded, f"{where}.{k}: missing from the loaded study"
                _assert_loaded(loaded[k], v, f"{where}.{k}")
            else:
                assert hasattr(loaded, k), f"{where}.{k}: missing from the loaded study"
                _assert_loaded(getattr(loaded, k), v, f"{where}.{k}")
    elif isinstance(raw, list):
        assert isinstance(loaded, list) and len(loaded) == len(raw), f"{where}: {loaded!r} != {raw!r}"
        for i, (a, b) in enumerate(zip(loaded, raw)):
            _assert_loaded(a, b, f"{where}[{i}]")
    elif isinstance(raw, (int, float)) and not isinstance(raw, bool):
        assert not isinstance(loaded, bool) and float(loaded) == float(raw), f"{where}: {loaded!r} != {raw!r}"
    else:
        assert loaded == raw and type(loaded) is type(raw), f"{where}: {loaded!r} != {raw!r}"


@pytest.mark.parametrize("name", [p.stem for p in paths.study_files()])
def test_committed_studies_load(name):
    """Each study file params/<name>.yaml (`paths.study_files`: not the claims, nor the data edits' file) loads,
    names itself <name> (so `monolib study <name>` and its runs/ folder agree), holds every value its file (and the
    file it extends) writes, and is a grid the runner can run."""
    file = paths.PARAMS / f"{name}.yaml"
    raw = yaml.safe_load(file.read_text())
    s = load_study(name, check_files=name in ("smoke", "quick"))
    assert s.name == raw["name"] == name
    assert s.path == str(file.resolve())
    if raw.get("extends"):
        base = yaml.safe_load((paths.PARAMS / f"{raw['extends']}.yaml").read_text())
        assert s.extends == raw["extends"] and not base.get("extends")
        assert s.data_dir == paths.study_dir(raw["extends"])    # the base's dataset, models and graphs are reused
        raw = _merged(base, raw)
        raw["name"] = name
    _assert_loaded(s, raw, name)
    # a grid the runner can read: every scenario of known models, every method known (a study may have no method:
    # params/zoo.yaml only pretrains perception networks)
    assert s.scenarios and s.thresholds and s.seeds
    models = set(s.model_names()) | {"gt"}
    assert all({sc.depth, sc.semantic} <= models for sc in s.scenarios.values())
    assert all(s.method_kind(m) in ("graph", "image") for m in s.methods + list(s.variants))
    assert s.protocol.queries + s.protocol.positives == s.protocol.frames


def test_quick_is_the_papers_protocol():
    s = load_study("quick")
    assert (s.protocol.settings, s.protocol.frames, s.protocol.queries, s.protocol.positives) == (16, 41, 35, 6)
    assert s.protocol.siblings == 8 and s.dataset.test_siblings == 8   # the siblings protocol: 8 families of 2
    assert s.thresholds == [0.0, 1.0, 2.0, 5.0, 10.0, math.inf]        # 0: no edges
    assert len(s.scenarios) == 4 and len(s.seeds) >= 3


def write(tmp_path, change):
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    change(data)
    p = tmp_path / "study.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.parametrize("change, key", [
    (lambda d: d.update(colour=1), "colour: unknown key"),
    (lambda d: d["dataset"].update(widht=3), "dataset.widht: unknown key"),
    (lambda d: d["dataset"].update(width="big"), "dataset.width: expected an integer"),
    (lambda d: d["protocol"].update(queries=99), "protocol.queries"),
    (lambda d: d["scenarios"]["s3"].update(depth="midas"), "scenarios.s3.depth"),
    (lambda d: d.update(thresholds=[-1]), "thresholds"),
    (lambda d: d["scenarios"]["s2"].update(thresholds=[-0.5]), "scenarios.s2.thresholds"),
    (lambda d: d["protocol"].update(siblings=-1), "protocol.siblings: expected 0"),
    (lambda d: d["protocol"].update(siblings=3), "protocol.siblings: 3 families of 2 settings asked"),
    (lambda d: d["dataset"].update(test_siblings=5), "dataset.test_siblings"),
    (lambda d: d.update(methods=["magic"]), "methods: unknown method 'magic'"),
    (lambda d: d["perception"]["depth"][0].update(checkpoint="/nope.pt", backbone="resnet50"),
     "perception.depth\\[0\\].checkpoint"),
    (lambda d: d.update(variants={"v": {"gcn": {"poolng": "max"}}}), "variants.v.gcn.poolng: unknown key"),
    (lambda d: d.update(variants={"v": {"gcn": {"pooling": "sum"}}}),
     "variants.v.gcn.pooling: expected one of max, meanmax"),
    (lambda d: d["gcn"].update(schedule="linear"), "gcn.schedule: expected one of constant, cosine, got 'linear'"),
    (lambda d: d["gcn"].update(node_order="random"), "gcn.node_order: expected one of label, reversed, shuffled"),
    (lambda d: d.update(variants={"v": {"gcn": {"edges": "both", "node_order": "reversed"}}}),
     "variants.v.gcn.node_order: orders the edges of edges: upper; with edges: both"),
    (lambda d: d.update(variants={"v": {"scenarios": ["s9"]}}), "variants.v.scenarios: unknown scenario 's9'"),
    (lambda d: d.update(variants={"gcn": {}}), "variants.gcn: a variant cannot reuse the name"),
    (lambda d: d["perception"]["segmentation"].update(backbone="efficientnet_lite9"),
     "perception.segmentation.backbone: expected one of .*efficientnet_lite2"),
    (lambda d: d["perception"]["segmentation"].update(backbone="efficientnet_lite0", train_height=72, train_width=96),
     "perception.segmentation.train_height: DeepLabV3 on efficientnet_lite0 needs .* multiples of 32"),
    (lambda d: d["perception"]["depth"][1].update(backbone="efficientnet_b0"),
     "perception.depth\\[1\\].backbone: expected one of"),
    (lambda d: d["graphs"].update(projection="pinhole"),
     "graphs.projection: expected one of monograph, exact, got 'pinhole'"),
    (lambda d: d["graphs"].update(camera="exact"), "graphs.camera: unknown key"),
    (lambda d: d["scenarios"]["s2"].update(projection="true"),
     "scenarios.s2.projection: expected one of monograph, exact"),
    (lambda d: (d.update(graphs_root=".", scenarios={"s1": {"depth": "gt", "semantic": "gt", "projection": "exact"}})),
     "scenarios.s1.projection: published graphs hold the original code's lengths"),
])
def test_bad_study_names_the_key(tmp_path, change, key):
    with pytest.raises(StudyError, match=key):
        load_study(write(tmp_path, change))


@pytest.mark.parametrize("change, key, new", [
    (lambda d: d["gcn"].update(label="embedding"), "gcn.label", "label_encoding"),
    (lambda d: d["gcn"].update(colour="standardised"), "gcn.colour", "colour_encoding"),
    (lambda d: d.update(variants={"ours": {"gcn": {"pooling": "meanmax", "label": "embedding"}}}),
     "variants.ours.gcn.label", "label_encoding"),
    (lambda d: d.update(variants={"ours": {"gcn": {"colour": "standardised"}}}),
     "variants.ours.gcn.colour", "colour_encoding"),
])
def test_an_encoders_old_key_is_told_its_new_name(tmp_path, change, key, new):
    """The encoder's `label` and `colour` (how it reads a node's NYU40 id and colour) are `label_encoding` and
    `colour_encoding`: a study file that still gives the old key gets one error naming the file, the key and the new
    name; a scenario's `label` and `colour` and `graphs.colour` keep their names."""
    path = write(tmp_path, change)
    with pytest.raises(StudyError) as err:
        load_study(path)
    assert str(err.value) == f"{path.resolve()}: {key}: renamed to {new}"
    with pytest.raises(Exception, match=f"{key.rsplit('.', 1)[1]}: renamed to {new}"):
        GCNSpec(**{key.rsplit(".", 1)[1]: "raw"})


def test_unknown_study_lists_the_known_ones():
    with pytest.raises(StudyError, match="smoke"):
        load_study("no_such_study")


def test_missing_data_folder_names_the_key(tmp_path):
    p = tmp_path / "study.yaml"
    p.write_text((paths.PARAMS / "published.yaml").read_text().replace("runs/published_graphs", str(tmp_path / "nope")))
    with pytest.raises(StudyError, match="graphs_root: folder not found"):
        load_study(p)


@pytest.mark.parametrize("where", ["params", "elsewhere"])
def test_relative_paths_resolve_against_the_project_root(tmp_path, monkeypatch, where):
    """A relative path in a study file means a path under the project root, whether the file sits in params/ or in
    any other folder (documented in `monolib.params.resolve_path`); an absolute path is taken as it is."""
    monkeypatch.chdir(tmp_path)  # not the working directory either
    folder = (paths.PARAMS if where == "params" else tmp_path / "studies")
    folder.mkdir(exist_ok=True)
    graphs = tmp_path / "graphs"
    (graphs / "train").mkdir(parents=True)
    relative = os.path.relpath(graphs, paths.ROOT)
    text = (paths.PARAMS / "published.yaml").read_text()
    p = folder / f"_test_relative_{where}.yaml"
    try:
        p.write_text(text.replace("runs/published_graphs", relative))
        assert resolve_path(relative) == paths.ROOT / relative
        assert (paths.ROOT / load_study(p).graphs_root).resolve() == graphs.resolve()
        p.write_text(text.replace("runs/published_graphs", str(graphs)))
        assert resolve_path(load_study(p).graphs_root) == graphs
        p.write_text(text.replace("runs/published_graphs", "no/such/folder"))
        with pytest.raises(StudyError, match=f"graphs_root: folder not found: {paths.ROOT / 'no/such/folder'}"):
            load_study(p)
    finally:
        p.unlink(missing_ok=True)


def test_an_extending_study_merges_key_by_key(tmp_path):
    """`extends:` takes the base file as defaults; mappings merge, lists are replaced, and a mapping the extending
    file re-lists completely keeps its own order (the ablations study puts quick's `ours` last)."""
    base = tmp_path / "base.yaml"
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["variants"] = {"ours": {"gcn": {"pooling": "meanmax"}, "thresholds": [2]}}
    base.write_text(yaml.safe_dump(data))
    child = tmp_path / "child.yaml"
    child.write_text(yaml.safe_dump({
        "name": "child", "extends": str(base), "seeds": [5],
        "scenarios": {"s9": {"depth": "gt", "semantic": "gt"}},
        "variants": {"gine": {"gcn": {"conv": "gine"}}, "ours": {"thresholds": None}}}))
    s = load_study(child)
    assert s.seeds == [5]
    assert list(s.scenarios)[-1] == "s9" and list(s.scenarios)[:-1] == list(data["scenarios"])
    assert list(s.variants) == ["gine", "ours"]
    assert s.variants["ours"].gcn == {"pooling": "meanmax"} and s.variants["ours"].thresholds is None
    assert load_study(base).variants["ours"].thresholds == [2.0]


def test_an_extending_study_removes_what_it_sets_to_null(tmp_path):
    """A scenario or variant of the base that the extending file sets to null is not in the study (the colour study
    keeps two of quick's scenarios); a list set to null is a null value, as before. quick's `more_seeds` name
    cells of s2 and s4: a study without them sets its own (one error naming the key otherwise)."""
    child = tmp_path / "child.yaml"
    data = {"name": "child", "extends": "quick", "scenarios": {"s2": None, "s4": None},
            "variants": {"layout": None, "ours": {"thresholds": None}}}
    child.write_text(yaml.safe_dump(data))
    with pytest.raises(StudyError, match="more_seeds\\[0\\].scenarios: gcn does not run on scenario 's2'"):
        load_study(child)
    child.write_text(yaml.safe_dump({**data, "more_seeds": []}))
    s = load_study(child)
    assert list(s.scenarios) == ["s1", "s3"] and list(s.variants) == ["ours"]
    assert s.variants["ours"].thresholds is None
    assert list(load_study("quick").scenarios) == ["s1", "s2", "s3", "s4"]


def test_threshold_zero_and_no_siblings_protocol_are_allowed(tmp_path):
    """0 is a threshold (no edges); `protocol.siblings: 0` is a study with the paper protocol only (as the real-data
    studies are)."""
    s = load_study(write(tmp_path, lambda d: (d.update(thresholds=[0, 1]), d["protocol"].update(siblings=0))))
    assert s.thresholds == [0.0, 1.0] and s.protocol.siblings == 0
    assert paths.threshold_tag(0) == "0" and paths.threshold_tag(-0.0) == "0"
    for name in ("paper", "published"):
        assert load_study(name, check_files=False).protocol.siblings == 0
    assert load_study("smoke").protocol.siblings == 2 and load_study("smoke").thresholds[0] == 0.0


@pytest.mark.parametrize("change, key", [
    (lambda d: d.update(jobs=0), "jobs: expected at least 1, got 0"),
    (lambda d: d.update(threads=0), "threads: expected at least 1, got 0"),
    (lambda d: d["perception"].update(threads=0), "perception.threads: expected at least 1"),
    (lambda d: d["perception"]["segmentation"].update(epochs=0), "perception.segmentation.epochs: expected at least 1"),
    (lambda d: d["perception"]["segmentation"].update(batch_size=1),
     "perception.segmentation.batch_size: expected at least 2"),
    (lambda d: d["perception"]["depth"][0].update(batch_size=1),
     "perception.depth\\[0\\].batch_size: expected at least 2"),
    (lambda d: d["gcn"].update(epochs=0), "gcn.epochs: expected at least 1, got 0"),
    (lambda d: d["gcn"].update(layers=0), "gcn.layers: expected at least 1, got 0"),
    (lambda d: d["protocol"].update(precision_k=[2, 0]), "protocol.precision_k\\[1\\]: expected at least 1, got 0"),
    (lambda d: d["protocol"].update(recall_k=[0]), "protocol.recall_k\\[0\\]: expected at least 1, got 0"),
    (lambda d: d["gcn"].update(batch_size=0), "gcn.batch_size: expected at least 1"),
    (lambda d: d["dataset"].update(base_train_settings=7),
     "dataset.base_train_settings: expected 1..train_settings \\(6\\), got 7"),
    (lambda d: d["dataset"].update(base_train_settings=0),
     "dataset.base_train_settings: expected 1..train_settings \\(6\\), got 0"),
    (lambda d: d.update(seeds=[0, 0]), "seeds: each seed once"),
    (lambda d: d.update(thresholds=[1, 2.5, 2.5]), "thresholds: 2.5 and 2.5 name the same cell folder"),
    (lambda d: d.update(thresholds=[2.5, 2.5000000000001]),
     "thresholds: 2.5 and 2.5000000000001 name the same cell folder"),
    (lambda d: d["scenarios"]["s2"].update(thresholds=[1, 1.0]), "scenarios.s2.thresholds: 1.0 and 1.0 name the same"),
    (lambda d: d.update(more_seeds=[{"method": "gnc", "scenarios": ["s1"], "thresholds": [0], "seeds": [1]}]),
     "more_seeds\\[0\\].method: expected a graph method of the study \\(gcn"),
    (lambda d: d.update(more_seeds=[{"method": "gcn", "scenarios": ["s9"], "thresholds": [0], "seeds": [1]}]),
     "more_seeds\\[0\\].scenarios: gcn does not run on scenario 's9'"),
    (lambda d: d.update(more_seeds=[{"method": "gcn", "scenarios": ["s1"], "thresholds": [3], "seeds": [1]}]),
     "more_seeds\\[0\\].thresholds: 3 m is not a threshold of gcn on s1"),
    (lambda d: d.update(more_seeds=[{"method": "gcn", "scenarios": ["s1"], "thresholds": [0], "seeds": [0, 1]}]),
     "more_seeds\\[0\\].seeds: seeds \\[0\\] are already the study's seeds"),
    (lambda d: d.update(more_seeds=[{"method": "gcn", "scenarios": ["s1"], "thresholds": [0], "seeds": [1]},
                                    {"method": "gcn", "scenarios": ["s1", "s2"], "thresholds": [0], "seeds": [1]}]),
     "more_seeds\\[1\\].seeds: seed 1 of gcn on s1 at 0 m is already in more_seeds\\[0\\]"),
    (lambda d: d.update(more_seeds=[{"method": "gcn", "scenarios": ["s1"], "thresholds": [0]}]),
     "more_seeds\\[0\\].seeds: missing \\(each entry needs method, scenarios, thresholds, seeds\\)"),
    (lambda d: d.update(more_seeds=[{"method": "gcn", "scenarios": ["s1"], "thresholds": [0], "seeds": []}]),
     "more_seeds\\[0\\].seeds: expected at least one seed"),
    (lambda d: d.update(image_training={"orb_bow": {"lr": 0.01}}),
     "image_training.orb_bow: not a learned image encoder \\(those trained with the triplet loss: image_triplet, "
     "imagenet_triplet"),
    (lambda d: d.update(image_training={"image_triplet": {"hidden": 32}}),
     "image_training.image_triplet.hidden: expected one of epochs, lr, schedule"),
    (lambda d: d.update(image_training={"image_triplet": {"epochs": 0}}),
     "image_training.image_triplet.epochs: expected at least 1, got 0"),
    (lambda d: d.update(image_training={"imagenet_triplet": {"select": "best"}}),
     "image_training.imagenet_triplet.select: expected one of val_recall"),
    (lambda d: d.update(image_training={"imagenet_triplet": 0.001}),
     "image_training.imagenet_triplet: expected a mapping, got 0.001"),
])
def test_values_the_code_cannot_use_are_refused_when_the_study_loads(tmp_path, change, key):
    """Each bad value: one StudyError naming the key and what is expected, before any work."""
    with pytest.raises(StudyError, match=key):
        load_study(write(tmp_path, change))


@pytest.mark.parametrize("change, message", [
    (lambda d: d["dataset"].update(width=2000), "dataset.width: expected 16..1024, got 2000"),
    (lambda d: d["dataset"].update(source="real"), "dataset.source: expected one of synth, hypersim, got 'real'"),
    (lambda d: d["perception"]["depth"][1].update(backbone="vgg16"),
     "perception.depth[1].backbone: expected one of resnet18, resnet34, resnet50, resnet101, resnext50_32x4d, "
     "resnext101_32x8d, efficientnet_lite0, efficientnet_lite1, efficientnet_lite2, got 'vgg16'"),
    (lambda d: d["perception"]["depth"][0].update(nme="x"),
     "perception.depth[0].nme: unknown key (allowed: backbone, batch_size, checkpoint, decoder_width, epochs, lr, "
     "name, pretrained, role, train_height, train_width, val_settings, weight_decay, weights)"),
    (lambda d: d["scenarios"]["s2"].update(depth_scale=0), "scenarios.s2.depth_scale: expected > 0, got 0"),
    (lambda d: d["gcn"].update(lr="fast"), "gcn.lr: expected a number (or 'inf'), got 'fast'"),
    (lambda d: d["gcn"].update(family_share=2), "gcn.family_share: expected a share in [0, 1], got 2"),
    (lambda d: d["gcn"].update(min_epochs=9), "gcn.min_epochs: expected 1 .. epochs (3), got 9"),
    (lambda d: d.update(seeds=[True]), "seeds[0]: expected an integer, got True"),
    (lambda d: d.update(thresholds=[]), "thresholds: expected a non-empty list, got []"),
    (lambda d: d.update(scenarios={}), "scenarios: expected a non-empty mapping, got {}"),
    (lambda d: d.update(variants={"v": {"thresholds": [1, -2]}}),
     "variants.v.thresholds[1]: expected a distance in metres >= 0 (0: no edges; inf: all pairs), got -2"),
    (lambda d: d.update(variants={"v": 3}),
     "variants.v: expected a mapping of ['ablation_of', 'description', 'gcn', 'scenarios', 'thresholds'], got 3"),
    (lambda d: d.update(methods="gcn"), "methods: expected a list, got 'gcn'"),
    (lambda d: d.update(path="x.yaml"), "path: unknown key (allowed: cell_timeout, dataset, deterministic, extends, "
     "gcn, graphs, graphs_root, image_training, jobs, methods, more_seeds, name, perception, protocol, scenarios, "
     "seed, seeds, threads, thresholds, variants)"),
    (lambda d: d["perception"]["depth"][1].update(name="depth_a"),
     "perception: model names must be unique and not 'gt', got ['deeplab', 'depth_a', 'depth_a']"),
    (lambda d: d["dataset"].update(width=100), "dataset.width: Hypersim frames are 4:3; got 100x96"),
])
def test_each_error_is_one_line_naming_the_key_the_expected_and_the_value(tmp_path, change, message):
    """A type, a choice, a bound, an unknown key, a rule of one spec or between specs: whichever part of the schema
    refuses a value, the error is the file, the exact key (list items by index), what was expected and the value."""
    path = write(tmp_path, change)
    with pytest.raises(StudyError) as refused:
        load_study(path)
    assert str(refused.value) == f"{path}: {message}"


def test_specs_built_in_code_are_checked_by_the_same_schema():
    """The schema is the specs' own: a spec built in code meets the same choices, bounds and rules as one read from
    a file, and `dataclasses.replace` checks again."""
    with pytest.raises(ValueError, match="conv"):
        GCNSpec(conv="sage")
    with pytest.raises(ValueError, match="min_epochs"):
        dataclasses.replace(GCNSpec(epochs=3), min_epochs=4)
    assert dataclasses.asdict(GCNSpec(lr=1)) == {**dataclasses.asdict(GCNSpec()), "lr": 1.0}


def test_the_study_file_reference_is_written_from_the_schema():
    """docs/study-file.md is what `make study-file-doc` writes from the schema now, and it has a row with a meaning
    for every key of every spec a study file holds."""
    assert study_file_doc.PAGE.read_text() == study_file_doc.reference(), "docs/study-file.md: make study-file-doc"
    text = study_file_doc.PAGE.read_text()
    found = study_file_doc.sections()
    assert [spec for _, spec in found] == [Study, DatasetSpec, GraphsSpec, PerceptionSpec, SegmentationSpec,
                                           DepthSpec, Scenario, MoreSeeds, GCNSpec, Variant, Protocol]
    for key, spec in found:
        assert f"## {study_file_doc.title(key)}\n" in text
        for name in study_keys(spec):
            assert spec.__pydantic_fields__[name].description, f"{key}.{name}: no description"
            assert f"| `{name}` |" in text, f"{key}.{name}: not in docs/study-file.md"
    assert "| `path` |" not in text and "| `fold` |" not in text  # fields of a loaded study, not keys of the file


def test_image_training_trains_the_image_encoders_and_nothing_else(tmp_path):
    """`image_training`: a learned image encoder's training keys over `gcn:`'s reach its spec and its cells' key;
    the graph encoders and the other image encoder keep theirs."""
    from monolib.retrieval.cell import cell_key

    base = load_study(write(tmp_path, lambda d: d.update(methods=["gcn", "image_triplet", "imagenet_triplet"])))
    study = load_study(write(tmp_path, lambda d: d.update(methods=["gcn", "image_triplet", "imagenet_triplet"],
                                                          image_training={"imagenet_triplet": {"lr": 0.0003,
                                                                                               "epochs": 7}})))
    spec = study.gcn_spec("imagenet_triplet")
    assert (spec.lr, spec.epochs) == (0.0003, 7) and spec.hidden == study.gcn.hidden
    assert study.gcn_spec("image_triplet") == study.gcn_spec("gcn") == study.gcn == base.gcn
    key = lambda s, m: cell_key(s, m, "rgb", math.inf, 0, inputs="same")  # noqa: E731
    assert key(study, "imagenet_triplet") != key(base, "imagenet_triplet")
    assert key(study, "image_triplet") == key(base, "image_triplet")


def test_projection_is_a_study_key_each_scenario_may_override(tmp_path):
    """`graphs.projection` (default the paper's `monograph`), a scenario's own `projection`, and both in the graph
    stage's key (and so in every cell's)."""
    from monolib.graphs import scenegraphs

    for name in ("quick", "paper", "ablations", "smoke", "published"):
        assert load_study(name, check_files=False).graphs.projection == "monograph", name
    ablations = load_study("ablations", check_files=False)
    assert ablations.projection("s1_exact") == "exact" and ablations.projection("s1") == "monograph"

    def exact(d):
        d["graphs"]["projection"] = "exact"
        d["scenarios"]["s2"]["projection"] = "monograph"
    study = load_study(write(tmp_path, exact))
    assert study.projection("s1") == "exact" and study.projection("s2") == "monograph"
    key = scenegraphs.scenario_key(study, "s1")
    study.graphs.projection = "monograph"
    assert scenegraphs.scenario_key(study, "s1") != key
    assert load_study(write(tmp_path, lambda d: d.pop("graphs"))).graphs.projection == "monograph"


def test_close_thresholds_get_folders_of_their_own(tmp_path):
    s = load_study(write(tmp_path, lambda d: d.update(thresholds=[2.5, 2.5000001])))
    assert [paths.threshold_tag(t) for t in s.thresholds] == ["2.5", "2.5000001"]


def test_more_seeds_add_cells_to_the_grid_and_nowhere_else(tmp_path):
    """`more_seeds`: the named cells of one method run with the extra seeds as well, right after the study's seeds
    of the same cell; every other cell keeps the study's seeds."""
    from monolib.retrieval.grid import grid

    base = load_study(write(tmp_path, lambda d: None))
    study = load_study(write(tmp_path, lambda d: d.update(more_seeds=[
        {"method": "gcn", "scenarios": ["s2", "s3"], "thresholds": [0, ".inf"], "seeds": [7, 3]}])))
    before, after = grid(base), grid(study)
    added = [c for c in after if c not in before]
    assert sorted((c.scenario, c.threshold, c.seed) for c in added) == sorted(
        (sc, t, s) for sc in ("s2", "s3") for t in (0.0, math.inf) for s in (7, 3))
    assert [c for c in after if c in before] == before
    i = after.index(added[0])
    assert (after[i - 1].method, after[i - 1].scenario, after[i - 1].threshold, after[i - 1].seed) == \
        ("gcn", "s2", 0.0, study.seeds[-1])
    assert [c.seed for c in after[i:i + 2]] == [7, 3]
