"""`depth.load_adelai_checkpoint` against the ORIGINAL AdelaiDepth LeReS checkpoint layout.

The key names and counts below are derived from AdelaiDepth's own code (aim-uofa/AdelaiDepth,
``LeReS/Minist_Test/lib/``), not from the project's model:

* ``multi_depth_model_woauxi.py``: ``RelDepthModel.depth_model = DepthModel(encoder)``;
  ``DepthModel.encoder_modules = network_auxi.resnet50_stride32()`` / ``resnext101_stride32x8d()`` and
  ``DepthModel.decoder_modules = network_auxi.Decoder()``.
* ``network_auxi.py``: ``DepthNet`` holds the ResNet as ``self.encoder`` (``Resnet.resnet50`` or
  ``Resnext_torch.resnext101_32x8d``); ``Decoder`` = ``conv`` (FTB 2048->512), ``conv1`` (Conv 512->256, bias),
  ``ffm2``/``ffm1``/``ffm0`` (FFM = ``ftb1`` + ``ftb2``), ``outconv`` (AO: ``adapt_conv`` = Conv(bias), BN, ReLU,
  Conv(bias), Upsample); FTB = ``conv1`` (bias) + ``conv_branch`` = ReLU, Conv(bias), BN, ReLU, Conv(bias).
* ``Resnet.py`` / ``Resnext_torch.py``: ``ResNet(Bottleneck, [3, 4, 6, 3])`` / ``[3, 4, 23, 3]`` (groups 32, width 8)
  with ``conv1``, ``bn1``, ``layer1..4`` and NO ``avgpool``/``fc`` (commented out); each Bottleneck has
  ``conv1..3`` (no bias) + ``bn1..3``, the first block of every layer a ``downsample`` = (Conv, BN).
* ``net_tools.py``: ``load_ckpt`` loads ``checkpoint['depth_model']`` with ``strict=True`` after
  ``strip_prefix_if_present(..., "module.")`` (stripped only when every key has it).

Each BatchNorm2d contributes 5 state-dict entries (weight, bias, running_mean, running_var, num_batches_tracked).
"""
from __future__ import annotations

import math

import pytest
import torch

from monolib.perception import depth

BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
ENC = "depth_model.encoder_modules.encoder."
DEC = "depth_model.decoder_modules."
# Resnet.resnet50, Resnext_torch.resnext101_32x8d
LAYERS = {"resnet50": (3, 4, 6, 3), "resnext101_32x8d": (3, 4, 23, 3)}


def _bn(p):
    return [f"{p}.{s}" for s in BN]


def original_resnet_keys(layers):
    """State-dict keys of AdelaiDepth's ResNet (Resnet.py / Resnext_torch.py: no avgpool, no fc)."""
    keys = ["conv1.weight", *_bn("bn1")]
    for li, blocks in enumerate(layers, start=1):
        for b in range(blocks):
            p = f"layer{li}.{b}"
            for j in (1, 2, 3):
                keys += [f"{p}.conv{j}.weight", *_bn(f"{p}.bn{j}")]
            if b == 0:  # layer1: 64 != 256 channels; layer2-4: stride 2
                keys += [f"{p}.downsample.0.weight", *_bn(f"{p}.downsample.1")]
    return keys


def _ftb(p):
    return [f"{p}.conv1.weight", f"{p}.conv1.bias", f"{p}.conv_branch.1.weight", f"{p}.conv_branch.1.bias",
            *_bn(f"{p}.conv_branch.2"), f"{p}.conv_branch.4.weight", f"{p}.conv_branch.4.bias"]


def original_decoder_keys():
    """State-dict keys of network_auxi.Decoder."""
    keys = [*_ftb("conv"), "conv1.weight", "conv1.bias"]
    for f in ("ffm2", "ffm1", "ffm0"):
        keys += [*_ftb(f"{f}.ftb1"), *_ftb(f"{f}.ftb2")]
    keys += ["outconv.adapt_conv.0.weight", "outconv.adapt_conv.0.bias", *_bn("outconv.adapt_conv.1"),
             "outconv.adapt_conv.3.weight", "outconv.adapt_conv.3.bias"]
    return keys


def original_keys(backbone):
    """All keys of checkpoint['depth_model'] (RelDepthModel.state_dict()), without 'module.'."""
    return [ENC + k for k in original_resnet_keys(LAYERS[backbone])] + [DEC + k for k in original_decoder_keys()]


def project_name(key):
    """Where the test expects an original key to land in the project's model (its encoder holds the ResNet)."""
    if key.startswith(ENC):
        return "encoder_modules." + key[len(ENC):]
    return key[len("depth_model."):]


def test_key_counts_from_original_code():
    assert len(original_decoder_keys()) == 88
    assert len(original_resnet_keys(LAYERS["resnet50"])) == 318
    assert len(original_resnet_keys(LAYERS["resnext101_32x8d"])) == 624
    assert len(original_keys("resnet50")) == 406
    assert len(original_keys("resnext101_32x8d")) == 712
    for b in LAYERS:
        assert len(set(original_keys(b))) == len(original_keys(b))


def shapes_of(backbone):
    """The project's model on the `meta` device: the names, shapes and dtypes of its state without the seconds of
    a random initialisation (ResNeXt101-32x8d holds 88M weights)."""
    with torch.device("meta"):
        return depth.build_leres(backbone)


def uninitialised(backbone):
    """The project's model with storage and no initialisation, for a strict load that overwrites every tensor."""
    return shapes_of(backbone).to_empty(device="cpu")


POOL = 1 << 20  # standard normal values that each tensor takes a slice of (tiled), at an offset of its own


def _normal(shape, pool: torch.Tensor, index: int) -> torch.Tensor:
    n = math.prod(shape)
    start = (index * 7919) % POOL
    return pool.repeat(-(-(start + n) // POOL))[start : start + n].reshape(shape).clone()


def random_original_state(model, backbone, seed=0):
    """Random tensors, in the original layout, of the shapes of `model`'s corresponding tensors (BN stats too):
    every tensor a slice of its own of one seeded pool of normal values, so that no two tensors are alike."""
    gen = torch.Generator().manual_seed(seed)
    pool = torch.randn(POOL, generator=gen)
    target = model.state_dict()
    state = {}
    for i, k in enumerate(original_keys(backbone)):
        ref = target[project_name(k)]  # KeyError here: the project's model lacks a tensor of the original
        if k.endswith("num_batches_tracked"):
            v = torch.randint(1, 10_000, (), generator=gen, dtype=ref.dtype)
        elif k.endswith("running_var"):
            v = 0.5 + _normal(ref.shape, pool, i).abs()
        elif k.endswith("running_mean") or k.endswith("bias"):
            v = 0.1 * _normal(ref.shape, pool, i)
        elif ref.dim() == 1:  # BN weight
            v = 1.0 + 0.1 * _normal(ref.shape, pool, i)
        else:  # conv weight, roughly variance-preserving so a deep forward stays finite
            v = _normal(ref.shape, pool, i) * (1.0 / math.prod(ref.shape[1:])) ** 0.5
        state[k] = v.to(ref.dtype)
    return state


def save(path, state, prefix=""):
    # The real files may hold other models too; load_ckpt reads only the entries it is asked for.
    torch.save({"depth_model": {prefix + k: v for k, v in state.items()},
                "shift_model": {"module.conv.weight": torch.zeros(1)}}, path)
    return path


def direct(backbone, state):
    """A model into which the same tensors are put directly (project names, load_state_dict)."""
    ref = uninitialised(backbone)
    ref.load_state_dict({project_name(k): v for k, v in state.items()}, strict=True)
    return ref.eval()


def assert_same_tensors(model, state):
    sd = model.state_dict()
    assert len(sd) == len(state)
    for k, v in state.items():
        assert torch.equal(sd[project_name(k)], v), k


@pytest.mark.parametrize("prefix", ["", "module."])
def test_resnet50_original_layout_loads(tmp_path, prefix):
    state = random_original_state(shapes_of("resnet50"), "resnet50")
    # spot checks of shapes against the original code (Resnet.py, network_auxi.py)
    assert state[ENC + "layer1.0.conv1.weight"].shape == (64, 64, 1, 1)
    assert state[ENC + "layer4.2.conv3.weight"].shape == (2048, 512, 1, 1)
    assert state[DEC + "conv.conv1.weight"].shape == (512, 2048, 3, 3)
    assert state[DEC + "conv1.weight"].shape == (256, 512, 3, 3)
    assert state[DEC + "ffm0.ftb1.conv1.weight"].shape == (256, 256, 3, 3)
    assert state[DEC + "outconv.adapt_conv.3.weight"].shape == (1, 128, 3, 3)
    path = save(tmp_path / "res50.pth", state, prefix)

    model = depth.load_adelai_checkpoint(depth.build_leres("resnet50"), path)
    assert not model.training and model.mode == "leres"
    assert_same_tensors(model, state)

    ref = direct("resnet50", state)
    x = torch.randn(1, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        out, want = model(x), ref(x)
        other = depth.build_leres("resnet50").eval()(x)  # different weights: the comparison means something
    assert out.shape == (1, 1, 64, 64) and torch.isfinite(out).all()
    torch.testing.assert_close(out, want, rtol=0, atol=0)
    assert not torch.allclose(out, other)


@pytest.mark.slow
def test_resnext101_original_layout_loads(tmp_path):
    state = random_original_state(shapes_of("resnext101_32x8d"), "resnext101_32x8d")
    # Resnext_torch.py: width = planes * 8/64 * 32 -> 256 in layer1, grouped 3x3 conv (32 groups)
    assert state[ENC + "layer1.0.conv1.weight"].shape == (256, 64, 1, 1)
    assert state[ENC + "layer1.0.conv2.weight"].shape == (256, 8, 3, 3)
    assert state[ENC + "layer3.22.conv3.weight"].shape == (1024, 1024, 1, 1)
    path = save(tmp_path / "res101.pth", state, "module.")

    model = depth.load_adelai_checkpoint(uninitialised("resnext101_32x8d"), path)
    assert_same_tensors(model, state)
    x = torch.randn(1, 3, 32, 32, generator=torch.Generator().manual_seed(1))  # tiny: ResNeXt101 is heavy
    with torch.no_grad():
        out, want = model(x), direct("resnext101_32x8d", state)(x)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, want, rtol=0, atol=0)

    # the ResNeXt101 file into a ResNet50 model: wrong architecture, a ValueError naming the file
    with pytest.raises(ValueError, match=r"res101\.pth.*does not match.*0 missing keys; 306 unexpected keys.*; "
                                         r"[1-9]\d* keys of the wrong shape"):
        depth.load_adelai_checkpoint(uninitialised("resnet50"), path)


def test_project_layout_still_loads(tmp_path):
    src = depth.build_leres("resnet50")
    for m in src.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.normal_()
    path = tmp_path / "own.pth"
    torch.save({"depth_model": {f"module.depth_model.{k}": v for k, v in src.state_dict().items()}}, path)
    dst = depth.load_adelai_checkpoint(uninitialised("resnet50"), path)
    for (k, a), b in zip(src.state_dict().items(), dst.state_dict().values()):
        assert torch.equal(a, b), k


@pytest.fixture(scope="module")
def res50_state():
    return random_original_state(shapes_of("resnet50"), "resnet50")


def _load(tmp_path, state, name="bad.pth", prefix=""):
    return depth.load_adelai_checkpoint(uninitialised("resnet50"), save(tmp_path / name, state, prefix))


def test_missing_key_raises(tmp_path, res50_state):
    state = dict(res50_state)
    del state[ENC + "layer2.1.bn2.weight"]
    with pytest.raises(ValueError, match=r"bad\.pth.*1 missing keys \(e\.g\. encoder_modules\.layer2\.1\.bn2\.weight\)"
                                         r"; 0 unexpected keys; 0 keys of"):
        _load(tmp_path, state)


def test_missing_decoder_key_raises(tmp_path, res50_state):
    state = {k: v for k, v in res50_state.items() if not k.startswith(DEC + "outconv.")}
    with pytest.raises(ValueError, match=r"bad\.pth.*8 missing keys \(e\.g\. decoder_modules\.outconv\.adapt_conv"):
        _load(tmp_path, state)


def test_wrong_layout_raises(tmp_path, res50_state):
    state = {k.replace(ENC, "depth_model.encoder_modules.backbone."): v for k, v in res50_state.items()}
    # 53 BN counters tolerated
    with pytest.raises(ValueError, match=r"bad\.pth.*265 missing keys.*; 318 unexpected keys"):
        _load(tmp_path, state)
    no_depth_model = {k[len("depth_model."):]: v for k, v in res50_state.items()}
    with pytest.raises(ValueError, match=r"bad\.pth.*no keys under 'depth_model\.'"):
        _load(tmp_path, no_depth_model)


def test_module_prefix_only_stripped_when_on_every_key(tmp_path, res50_state):
    """As strip_prefix_if_present: a partly prefixed dict keeps its prefixes, so strict loading fails."""
    state = {("module." + k if k.startswith(DEC) else k): v for k, v in res50_state.items()}
    with pytest.raises(ValueError, match=r"bad\.pth.*80 missing keys.*; 88 unexpected keys "
                                         r"\(e\.g\. module\.depth_model\.decoder"):
        _load(tmp_path, state)


def test_extra_and_duplicate_keys_raise(tmp_path, res50_state):
    state = dict(res50_state)
    state["depth_model.encoder_modules.encoder.fc.weight"] = torch.zeros(1000, 2048)
    with pytest.raises(ValueError, match=r"bad\.pth.*0 missing keys; 1 unexpected keys "
                                         r"\(e\.g\. depth_model\.encoder_modules\.encoder\.fc"):
        _load(tmp_path, state)
    both = dict(res50_state)
    both["depth_model.encoder_modules.conv1.weight"] = res50_state[ENC + "conv1.weight"]
    with pytest.raises(ValueError, match=r"bad\.pth.*0 missing keys; 1 unexpected keys "
                                         r"\(e\.g\. depth_model\.encoder_modules\.conv1\.weight\)"):
        _load(tmp_path, both)


def test_wrong_shape_and_unreadable_file_raise(tmp_path, res50_state):
    state = dict(res50_state)
    state[DEC + "conv1.weight"] = torch.zeros(128, 512, 3, 3)
    with pytest.raises(ValueError, match=r"bad\.pth.*1 keys of the wrong shape \(e\.g\. decoder_modules\.conv1\.weight "
                                         r"\(128, 512, 3, 3\) vs \(256, 512, 3, 3\)"):
        _load(tmp_path, state)
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"junk\.pth"):
        depth.load_adelai_checkpoint(uninitialised("resnet50"), tmp_path / "junk.pth")


def test_missing_batch_counters_tolerated(tmp_path, res50_state):
    """Files from PyTorch < 0.4.1 lack num_batches_tracked; PyTorch's strict load (and the original's) accepts that."""
    state = {k: v for k, v in res50_state.items() if not k.endswith("num_batches_tracked")}
    assert len(state) == 406 - 53 - 8  # 53 encoder + 8 decoder BatchNorms
    model = _load(tmp_path, state, "old.pth")
    sd = model.state_dict()
    for k, v in state.items():
        assert torch.equal(sd[project_name(k)], v), k
