"""Study files: the committed ones load; bad ones fail with one error naming the key."""
import math

import pytest
import yaml

from monolib import paths
from monolib.params import StudyError, load_study


@pytest.mark.parametrize("name", sorted(p.stem for p in paths.PARAMS.glob("*.yaml")))
def test_committed_studies_load(name):
    s = load_study(name, check_files=name in ("smoke", "quick"))
    assert s.name == name or s.path.endswith(f"{name}.yaml")


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
    (lambda d: d["perception"]["depth"][0].update(checkpoint="/nope.pt", backbone="resnet50"), "perception.depth\\[0\\].checkpoint"),
    (lambda d: d.update(variants={"v": {"gcn": {"poolng": "max"}}}), "variants.v.gcn.poolng: unknown key"),
    (lambda d: d.update(variants={"v": {"gcn": {"pooling": "sum"}}}), "variants.v.gcn.pooling: expected one of max, meanmax"),
    (lambda d: d.update(variants={"v": {"scenarios": ["s9"]}}), "variants.v.scenarios: unknown scenario 's9'"),
    (lambda d: d.update(variants={"gcn": {}}), "variants.gcn: a variant cannot reuse the name"),
])
def test_bad_study_names_the_key(tmp_path, change, key):
    with pytest.raises(StudyError, match=key):
        load_study(write(tmp_path, change))


def test_unknown_study_lists_the_known_ones():
    with pytest.raises(StudyError, match="smoke"):
        load_study("no_such_study")


def test_missing_data_folder_names_the_key(tmp_path):
    p = tmp_path / "study.yaml"
    p.write_text((paths.PARAMS / "published.yaml").read_text().replace("runs/published_graphs", str(tmp_path / "nope")))
    with pytest.raises(StudyError, match="graphs_root: folder not found"):
        load_study(p)


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


def test_threshold_zero_and_no_siblings_protocol_are_allowed(tmp_path):
    """0 is a threshold (no edges); `protocol.siblings: 0` is a study with the paper protocol only (as the real-data
    studies are)."""
    s = load_study(write(tmp_path, lambda d: (d.update(thresholds=[0, 1]), d["protocol"].update(siblings=0))))
    assert s.thresholds == [0.0, 1.0] and s.protocol.siblings == 0
    assert paths.threshold_tag(0) == "0" and paths.threshold_tag(-0.0) == "0"
    for name in ("paper", "published"):
        assert load_study(name, check_files=False).protocol.siblings == 0
    assert load_study("smoke").protocol.siblings == 2 and load_study("smoke").thresholds[0] == 0.0
