"""Image methods that start from ImageNet: what a practitioner of visual place recognition tries first.

All three read the ImageNet EfficientNet-Lite2 features of the frames (`monolib.perception.features`: the trunk's
output, stored once per dataset, and the classifier's last 1x1 convolution on top, the *head*: 1280 channels at
stride 32, 6 x 8 positions at 256x192).

- `imagenet_gem`: the head's feature map, generalised-mean pooled (p = 3, Radenović et al., TPAMI 2018), then
  L2-normalised. No training, no study data seen: the off-the-shelf global descriptor.
- `imagenet_vlad`: the same local features (each position's 1280-d vector, L2-normalised), aggregated AnyLoc's way
  (Keetha et al., RA-L 2023): a k-means vocabulary of `VLAD_WORDS` words learnt on the training split's features
  (seeded), hard-assignment VLAD with intra-normalisation, then L2; with `VLAD_WHITEN` dimensions, PCA-whitened
  on the training split's VLAD vectors and L2-normalised again.
- `imagenet_triplet`: the learnt image baseline from ImageNet: the head (initialised from ImageNet) and GeM,
  L2-normalised (`TRIPLET_OUT`: no projection), fine-tuned with the GCN's triplet loss, triplets and split, trained
  as the study's `image_training.imagenet_triplet` says (its learning rate and epochs, chosen on the training split
  by `monolib bench selection`) (`monolib.retrieval.training.train`, the loop of every triplet encoder, over the
  from-scratch `image_triplet`'s batches). The trunk stays
  frozen, as NetVLAD trains only the last convolutional block of its network (Arandjelović et al., CVPR 2016):
  its features are computed once per frame, so that the fine-tuning fits the study's CPU budget; the augmentation
  is a horizontal flip of the feature map (colour jitter would need the trunk again).
"""
from __future__ import annotations

import copy
import time

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from torch import nn

from monolib import methods
from monolib.device import device
from monolib.perception import features
from monolib.retrieval import training
from monolib.retrieval.baselines import image_batches, sample_indices, seeded_kmeans
from monolib.retrieval.training import TrainingRule, TrainResult, training_rule

METHODS = methods.IMAGENET  # (the registry's list of the image methods that read ImageNet features)
GEM_P = 3.0
GEM_EPS = 1e-6
VLAD_WORDS = 32
VLAD_SAMPLE = 20_000      # local descriptors the vocabulary is learnt from (seeded subsample of the training split)
VLAD_ITERS = 20
VLAD_WHITEN = None        # PCA-whitened dimensions (None: VLAD as it is; whitening lost 4-14 points of recall@1
                          # on quick, learnt from its 960 training vectors: `monolib bench imagenet`)
# The fine-tuned encoder's output: the GeM vector L2-normalised, no projection, so that training starts from the
# off-the-shelf `imagenet_gem` and the pretrained head is fine-tuned rather than fed to a new random layer.
TRIPLET_OUT = None
HEAD_BATCH = 128


def gem(x: torch.Tensor, p: float = GEM_P, eps: float = GEM_EPS) -> torch.Tensor:
    """(N, C, h, w) non-negative feature maps -> (N, C): (mean over positions of x^p)^(1/p), x clamped at `eps`."""
    return x.clamp(min=eps).pow(p).mean(dim=(2, 3)).pow(1.0 / p)


def head_maps(head: nn.Module, trunk: np.ndarray | torch.Tensor, batch: int = HEAD_BATCH) -> torch.Tensor:
    """(N, 1280, h, w) float32 on the CPU: the head (eval mode, no gradient) over float16 trunk features, on the
    device of the head's weights."""
    head.eval()
    dev = next(head.parameters()).device
    trunk = torch.as_tensor(trunk)
    with torch.inference_mode():
        out = [head(trunk[s : s + batch].to(dev, torch.float32)).cpu() for s in range(0, len(trunk), batch)]
    return torch.cat(out) if out else torch.zeros((0, 0, 0, 0))


def gem_descriptors(maps: torch.Tensor) -> np.ndarray:
    """(N, C) float32: GeM of each map, L2-normalised."""
    return F.normalize(gem(maps), dim=1).numpy().astype(np.float32)


def local_descriptors(maps: torch.Tensor) -> torch.Tensor:
    """(N, h*w, C): each position's feature vector of each map, L2-normalised."""
    return F.normalize(maps.flatten(2).transpose(1, 2), dim=2)


def vocabulary_sample(head: nn.Module, trunk: np.ndarray | torch.Tensor, seed: int, sample: int = VLAD_SAMPLE,
                      batch: int = HEAD_BATCH) -> np.ndarray:
    """(min(sample, N*P), C) float32: the local descriptors of `seeded_kmeans`' seeded subsample of the N frames'
    N*P (frame-major), computed `batch` frames at a time and only the chosen rows kept, so that the training split's
    (N, P, C) descriptors are never held at once (at 8,640 frames they are 2.2 GB, and a few copies of them filled
    a 24 GB machine running two cells). The same rows, to the bit, as subsampling them all at once."""
    trunk = torch.as_tensor(trunk)
    if len(trunk) == 0:
        raise ValueError("imagenet_vlad: no local descriptor in the training split")
    per_frame = int(trunk.shape[2] * trunk.shape[3])
    chosen = sample_indices(len(trunk) * per_frame, sample, seed)
    parts = []
    for s in range(0, len(trunk), batch):
        desc = local_descriptors(head_maps(head, trunk[s : s + batch], batch))
        desc = desc.reshape(-1, desc.shape[-1]).numpy()
        if chosen is not None:
            lo, hi = np.searchsorted(chosen, [s * per_frame, s * per_frame + len(desc)])
            desc = desc[chosen[lo:hi] - s * per_frame]
        parts.append(desc.astype(np.float32))
    return np.concatenate(parts)


def learn_vocabulary(desc: np.ndarray, seed: int, words: int = VLAD_WORDS, sample: int = VLAD_SAMPLE) -> np.ndarray:
    """(k, C) float32 k-means centres (`baselines.seeded_kmeans`: k-means++ init, seeded) of a seeded subsample of
    the (M, C) local descriptors (`vocabulary_sample`'s, which are that subsample already)."""
    if len(desc) == 0:
        raise ValueError("imagenet_vlad: no local descriptor in the training split")
    return seeded_kmeans(np.asarray(desc, np.float32), words, seed, sample, VLAD_ITERS, 1e-4)


def vlad(desc: torch.Tensor, centres: np.ndarray) -> np.ndarray:
    """(N, k*C) float32 VLAD of (N, P, C) local descriptors: each descriptor assigned to its nearest centre, the
    residuals to each centre summed, each centre's sum L2-normalised (intra-normalisation; a centre nothing is
    assigned to stays zero), the whole vector L2-normalised."""
    c = torch.from_numpy(centres).to(desc.dtype)
    n, _, dim = desc.shape
    if n == 0:
        return np.zeros((0, len(c) * dim), np.float32)
    nearest = torch.cdist(desc, c.expand(n, *c.shape)).argmin(dim=2)           # (N, P)
    one_hot = F.one_hot(nearest, len(c)).to(desc.dtype)                          # (N, P, k)
    residual = one_hot.transpose(1, 2) @ desc - one_hot.sum(1)[:, :, None] * c   # (N, k, C): sum of (x - c_k)
    return F.normalize(F.normalize(residual, dim=2).flatten(1), dim=1).numpy().astype(np.float32)


def learn_whitening(train: np.ndarray, dims: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean (D,), projection (D, d)): PCA of the training vectors, each of the `dims` leading components divided by
    its standard deviation (d = min(dims, rank))."""
    x = torch.from_numpy(np.asarray(train, np.float64))
    mean = x.mean(0)
    _, s, vh = torch.linalg.svd(x - mean, full_matrices=False)
    keep = int(min(dims, (s > s[0] * 1e-6).sum().item()))
    scale = s[:keep] / max(len(x) - 1, 1) ** 0.5
    return mean.numpy(), (vh[:keep].T / scale).numpy()


def whiten(x: np.ndarray, mean: np.ndarray, projection: np.ndarray) -> np.ndarray:
    y = (np.asarray(x, np.float64) - mean) @ projection
    return (y / np.maximum(np.linalg.norm(y, axis=1, keepdims=True), 1e-12)).astype(np.float32)


def vlad_embed(trunk_train: np.ndarray, trunk_test: np.ndarray, head: nn.Module, seed: int,
               words: int = VLAD_WORDS, whiten_dims=VLAD_WHITEN):
    """(test VLAD vectors, extra, state): the vocabulary (and the whitening) from the training split's features;
    `state` holds them (``centres``, and ``whiten_mean`` / ``whiten_projection``) for `describer`."""
    t = time.perf_counter()
    centres = learn_vocabulary(vocabulary_sample(head, trunk_train, seed), seed, words)
    test = vlad(local_descriptors(head_maps(head, trunk_test)), centres)
    extra = {"vlad_words": int(len(centres)), "local_per_frame": int(trunk_train.shape[2] * trunk_train.shape[3])}
    state = {"centres": torch.from_numpy(centres)}
    if whiten_dims:
        train = np.concatenate([vlad(local_descriptors(head_maps(head, trunk_train[s : s + HEAD_BATCH])), centres)
                                for s in range(0, len(trunk_train), HEAD_BATCH)])
        mean, projection = learn_whitening(train, whiten_dims)
        test = whiten(test, mean, projection)
        extra["whitened_dims"] = int(projection.shape[1])
        state.update(whiten_mean=torch.from_numpy(mean), whiten_projection=torch.from_numpy(projection))
    extra["vocab_s"] = time.perf_counter() - t
    return test, extra, state


class HeadEncoder(nn.Module):
    """The ImageNet head (1x1 conv + BN-ReLU6, a copy, trainable), GeM, then Linear to `out`, or with `out` None
    the GeM vector L2-normalised (the encoder then starts as `imagenet_gem`): the encoder `imagenet_triplet`
    fine-tunes over fixed trunk features."""

    def __init__(self, head: nn.Module, out: int | None = TRIPLET_OUT):
        super().__init__()
        self.head = copy.deepcopy(head)
        channels = [m for m in self.head.modules() if isinstance(m, nn.Conv2d)][-1].out_channels
        self.lin = nn.Linear(channels, out) if out else None
        self.out_channels = out or channels

    def forward(self, trunk: torch.Tensor) -> torch.Tensor:
        g = gem(self.head(trunk))
        return self.lin(g) if self.lin is not None else F.normalize(g, dim=1)


def head_embed(model: HeadEncoder, trunk: torch.Tensor, batch: int = HEAD_BATCH) -> torch.Tensor:
    """(N, out) embeddings of float16 trunk features, in order (eval mode), on the CPU."""
    model.eval()
    dev = next(model.parameters()).device
    with torch.inference_mode():
        out = [model(trunk[s : s + batch].to(dev, torch.float32)).cpu() for s in range(0, len(trunk), batch)]
    return torch.cat(out) if out else torch.zeros((0, model.out_channels))


def _flip(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """A batch of float16 trunk features as float32, each flipped left-right with probability 1/2."""
    flip = torch.rand(len(x), generator=gen) < 0.5
    x = x.float()
    return torch.where(flip[:, None, None, None], x.flip(3), x)


def train_head(head: nn.Module, trunk: dict, selection, *, rule: TrainingRule, seed: int, threads: int,
               deterministic: bool = True, on_epoch=None) -> TrainResult:
    """The `HeadEncoder` over `head` trained by `rule` (`monolib.retrieval.training.train`) on float16 trunk
    features (`trunk`: {"train", "val"}) of the selection's frames, flipped at random: the training of
    `imagenet_triplet`. `on_epoch(model)`, when given, adds columns to each epoch's history row."""
    batches = image_batches(torch.from_numpy(trunk["train"]), [f.setting for f in selection.train], rule, _flip)
    return training.train(lambda: HeadEncoder(head, TRIPLET_OUT), batches, rule=rule, seed=seed,
                          val_inputs=torch.from_numpy(trunk["val"]), val_settings=[f.setting for f in selection.val],
                          embed=head_embed, threads=threads, deterministic=deterministic, on_epoch=on_epoch)


def triplet_embed(study, selection, trunk, head: nn.Module, seed: int, rule: TrainingRule | None = None):
    """(test embeddings, extra, history, state) for `imagenet_triplet`; `trunk`: {split: float16 features};
    `rule` defaults to the study's training of the method (`Study.gcn_spec`: `gcn:` with `image_training`)."""
    rule = rule or training_rule(study.gcn_spec("imagenet_triplet"))
    te = torch.from_numpy(trunk["test"])
    result = train_head(head, trunk, selection, rule=rule, seed=seed, threads=study.threads,
                        deterministic=study.deterministic)
    emb = head_embed(result.model, te).numpy().astype(np.float32)
    extra = {"best_epoch": result.best_epoch, "epochs_run": len(result.history), "train_s": result.seconds,
             "trained_parameters": int(sum(p.numel() for p in result.model.parameters()))}
    state = {k: v.detach().cpu() for k, v in result.model.state_dict().items()}
    return emb, extra, pd.DataFrame(result.history), state


def embed(method: str, study, selection, seed: int):
    """Embeddings of `selection.test` for an ImageNet method: (emb (N, D) float32, extra info for cell.json,
    training history DataFrame or None, model state dict or None), as `monolib.retrieval.baselines.embed`."""
    if method not in METHODS:
        raise KeyError(f"image method {method!r}: not one of monolib.retrieval.pretrained's {', '.join(METHODS)}")
    torch.set_num_threads(study.threads)
    t = time.perf_counter()
    trunk = {"train": features.load(study, selection.train), "val": features.load(study, selection.val),
             "test": features.load(study, selection.test)}
    _, head = features.networks()
    head.to(device())
    extra = {"encoder": features.ENCODER, "load_s": time.perf_counter() - t}
    if method == "imagenet_gem":
        return gem_descriptors(head_maps(head, trunk["test"])), {**extra, "gem_p": GEM_P}, None, None
    if method == "imagenet_vlad":
        emb, more, state = vlad_embed(np.concatenate([trunk["train"], trunk["val"]]), trunk["test"], head, seed)
        return emb, {**extra, **more}, None, state
    emb, more, history, state = triplet_embed(study, selection, trunk, head, seed)
    return emb, {**extra, **more}, history, state


def describer(method: str, state: dict | None):
    """``describe(rgb) -> (N, D) float32``: the descriptor of `method` for a (N, H, W, 3) uint8 stack of new images
    at the study's resolution, as its cell computed the test frames' (`state`: the cell's ``model.pt``, for the
    VLAD vocabulary and the fine-tuned encoder). The ImageNet networks are loaded once, here."""
    if method not in METHODS:
        raise KeyError(f"image method {method!r}: not one of monolib.retrieval.pretrained's {', '.join(METHODS)}")
    trunk_net, head = features.networks()
    dev = device()
    trunk_net.to(dev)
    head.to(dev)
    model = None
    if method == "imagenet_triplet":
        model = HeadEncoder(head, TRIPLET_OUT)
        model.load_state_dict(state)
        model.to(dev).eval()

    def describe(rgb: np.ndarray) -> np.ndarray:
        trunk = features.trunk_features(trunk_net, rgb)
        if method == "imagenet_gem":
            return gem_descriptors(head_maps(head, trunk))
        if method == "imagenet_vlad":
            out = vlad(local_descriptors(head_maps(head, trunk)), state["centres"].numpy())
            if "whiten_mean" in state:
                out = whiten(out, state["whiten_mean"].numpy(), state["whiten_projection"].numpy())
            return out
        return head_embed(model, torch.from_numpy(trunk)).numpy().astype(np.float32)

    return describe
