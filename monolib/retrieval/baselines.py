"""Image-only retrieval baselines (no graph): they embed the RGB frame directly.

- `color_hist`: a global HSV colour histogram, no training (calibration baseline).
- `orb_bow`: ORB keypoints + a bag of visual words learnt on the training split, tf-idf weighted, L2-normalised
  (the classic hand-crafted place-recognition descriptor).
- `image_triplet`: the "texture-based" learnt global descriptor the paper argues against indoors: a small CNN on
  the RGB frame, trained from scratch with the GCN's triplet loss, triplets and data split, as long as the study's
  `image_training.image_triplet` says (chosen on the training split by `monolib bench selection`).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
import pandas as pd
import torch
from torch import nn

from monolib.device import device
from monolib.retrieval import training
from monolib.retrieval.training import TrainingRule, TrainResult, draw_triplets, training_rule, triplet_batches

log = logging.getLogger(__name__)

HIST_BINS = (8, 4, 4)  # hue, saturation, value


def _rgb(frame) -> np.ndarray:
    """A frame's uint8 RGB image; a frame without colour file reads as a black image of the dataset size."""
    rgb = frame.rgb
    if rgb is None:
        h, w = frame.depth_meters.shape
        rgb = np.zeros((h, w, 3), np.uint8)
    return np.ascontiguousarray(rgb)


# What a baseline computes from a frame's image alone, whatever the seed (a colour histogram, ORB's packed bits, the
# CNN's small image), kept per process by the identity of the frame's colour file (path, inode, mtime, size): the
# seeds of one method that a warm kernel runs in a row read and describe each frame once. A file rewritten is
# another identity, so nothing stale is returned; callers never modify what they get.
_PER_FRAME: dict[tuple, np.ndarray] = {}
PER_FRAME_ITEMS = 200_000  # about 10 datasets of quick's 1,944 frames x 3 kinds; then it starts again


def per_frame(frame, kind: str, compute) -> np.ndarray:
    """``compute(_rgb(frame))``, once per process for each (`kind`, colour file) (`_PER_FRAME`)."""
    path = (getattr(frame, "files", None) or {}).get("color")  # (a frame held in memory has no file)
    try:
        st = path.stat()
    except (AttributeError, OSError):  # no colour file: computed each time (no identity to keep it by)
        return compute(_rgb(frame))
    token = (kind, str(path), st.st_ino, st.st_mtime_ns, st.st_size)
    if token not in _PER_FRAME:
        if len(_PER_FRAME) >= PER_FRAME_ITEMS:
            _PER_FRAME.clear()
        _PER_FRAME[token] = compute(_rgb(frame))
    return _PER_FRAME[token]


def color_hist(rgb: np.ndarray) -> np.ndarray:
    """Global HSV colour histogram of a uint8 RGB image, L1-normalised then square-rooted (Hellinger), so that
    Euclidean distance between descriptors is a proper histogram distance."""
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)
    hist = cv2.calcHist([hsv], [0, 1, 2], None, list(HIST_BINS), [0, 180, 0, 256, 0, 256]).ravel()
    hist /= max(hist.sum(), 1.0)
    return np.sqrt(hist).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- ORB + BoW

ORB_FEATURES = 500
ORB_MIN_WIDTH = 256        # smaller images are upscaled first: ORB's 31-pixel patches leave little of a 128-px frame
BOW_WORDS = 192
BOW_SAMPLE = 10_000        # descriptors used to learn the vocabulary (seeded subsample)
KMEANS_ITERS = 10


def orb_descriptors(rgb: np.ndarray, n_features: int = ORB_FEATURES) -> np.ndarray:
    """(n, 256) float32 0/1: the unpacked bits of the ORB descriptors of the grey image (n may be 0)."""
    return np.unpackbits(orb_bits(rgb, n_features), axis=1).astype(np.float32)


def orb_bits(rgb: np.ndarray, n_features: int = ORB_FEATURES) -> np.ndarray:
    """(n, 32) uint8: the ORB descriptors of the grey image (n may be 0)."""
    grey = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
    if grey.shape[1] < ORB_MIN_WIDTH:
        f = ORB_MIN_WIDTH / grey.shape[1]
        grey = cv2.resize(grey, (ORB_MIN_WIDTH, round(grey.shape[0] * f)), interpolation=cv2.INTER_LINEAR)
    orb = cv2.ORB_create(nfeatures=n_features)
    _, desc = orb.detectAndCompute(grey, None)
    if desc is None or len(desc) == 0:
        return np.zeros((0, 32), np.uint8)
    return desc


@dataclass
class BagOfWords:
    """A visual vocabulary (k, 256) and the idf weight of each word, both learnt on training images."""
    centres: np.ndarray
    idf: np.ndarray

    def assign(self, desc: np.ndarray) -> np.ndarray:
        """Nearest word of each descriptor (squared Euclidean on the bits = Hamming for binary centres)."""
        d = (self.centres ** 2).sum(1)[None, :] - 2.0 * desc @ self.centres.T
        return d.argmin(1)

    def counts(self, desc: np.ndarray) -> np.ndarray:
        if len(desc) == 0:
            return np.zeros(len(self.centres), np.float32)
        return np.bincount(self.assign(desc), minlength=len(self.centres)).astype(np.float32)

    def describe(self, desc: np.ndarray) -> np.ndarray:
        """tf-idf histogram, L2-normalised (Euclidean distance then ranks like cosine); zero without keypoints."""
        c = self.counts(desc)
        if c.sum() == 0:
            return c
        v = c / c.sum() * self.idf
        n = np.linalg.norm(v)
        return (v / n if n > 0 else v).astype(np.float32)


def sample_indices(n: int, sample: int, seed: int) -> np.ndarray | None:
    """The sorted indices of `seeded_kmeans`' seeded subsample of `sample` of `n` points (None when n <= sample:
    every point). Callers that compute their points batch by batch draw the same subsample with it."""
    if n <= sample:
        return None
    return np.sort(np.random.default_rng(seed).choice(n, sample, replace=False))


def seeded_kmeans(points: np.ndarray, k: int, seed: int, sample: int, iters: int = KMEANS_ITERS,
                  eps: float = 1e-3) -> np.ndarray:
    """(min(k, n), D) float32 centres: cv2.kmeans (k-means++ init, one attempt, seeded) on a seeded subsample of
    `sample` of the (n, D) points. The one k-means of the visual vocabularies (ORB's here, VLAD's in
    `monolib.retrieval.pretrained`)."""
    chosen = sample_indices(len(points), sample, seed)
    if chosen is not None:
        points = points[chosen]
    cv2.setRNGSeed(int(seed))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, iters, eps)
    _, _, centres = cv2.kmeans(np.ascontiguousarray(points, dtype=np.float32), min(k, len(points)), None, criteria,
                               1, cv2.KMEANS_PP_CENTERS)
    return centres.astype(np.float32)


def learn_vocabulary(train_desc: list[np.ndarray], seed: int, words: int = BOW_WORDS,
                     sample: int = BOW_SAMPLE) -> BagOfWords:
    """k-means (`seeded_kmeans`) on a seeded subsample of the training descriptors; idf from the training images'
    word occurrences."""
    all_desc = np.concatenate([d for d in train_desc if len(d)] or [np.zeros((0, 256), np.float32)])
    if len(all_desc) == 0:
        raise ValueError("orb_bow: no ORB keypoint in any training image")
    centres = seeded_kmeans(all_desc, words, seed, sample)
    k = len(centres)
    bow = BagOfWords(centres, np.ones(k, np.float32))
    df = np.zeros(k)
    for d in train_desc:
        df += bow.counts(d) > 0
    bow.idf = np.log(len(train_desc) / np.maximum(df, 1.0)).astype(np.float32)
    return bow


def orb_bow_embed(selection, seed: int, words: int = BOW_WORDS):
    """(test embeddings, extra info, state) for `orb_bow`: vocabulary + idf from the training split (train + val);
    `state` holds them (``centres``, ``idf``) for `describer`."""
    t = time.perf_counter()
    describe = lambda f: np.unpackbits(per_frame(f, "orb", orb_bits), axis=1).astype(np.float32)  # noqa: E731
    train_desc = [describe(f) for f in selection.train + selection.val]
    bow = learn_vocabulary(train_desc, seed, words)
    vocab_s = time.perf_counter() - t
    test_desc = [describe(f) for f in selection.test]
    emb = np.stack([bow.describe(d) for d in test_desc]) if test_desc else np.zeros((0, len(bow.centres)), np.float32)
    extra = {"bow_words": int(len(bow.centres)), "vocab_s": vocab_s,
             "train_keypoints_mean": float(np.mean([len(d) for d in train_desc])),
             "test_keypoints_mean": float(np.mean([len(d) for d in test_desc])) if test_desc else 0.0,
             "test_no_keypoints": int(sum(len(d) == 0 for d in test_desc))}
    state = {"centres": torch.from_numpy(bow.centres), "idf": torch.from_numpy(bow.idf)}
    return emb.astype(np.float32), extra, state


# ------------------------------------------------------------------------------------------ CNN + triplet loss

CNN_SIZE = (48, 64)               # (height, width) the frames are resized to
CNN_STEM = 32                     # a 4x4 stride-4 "patchify" conv block first (cheap on a CPU) ...
CNN_CHANNELS = (64, 128, 128)     # ... then one 3x3 stride-2 conv block each
CNN_OUT = 64


def _block(c_in: int, c_out: int, kernel: int, stride: int, padding: int) -> list[nn.Module]:
    return [nn.Conv2d(c_in, c_out, kernel, stride, padding, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]


class ImageEncoder(nn.Module):
    """Conv-BN-ReLU blocks (a 4x4 stride-4 stem, then 3x3 stride-2), global average pool, Linear to `out`.

    At 48x64 input: 12x16 after the stem, 2x2 after the last block; about 0.26 M parameters."""

    def __init__(self, stem: int = CNN_STEM, channels=CNN_CHANNELS, out: int = CNN_OUT):
        super().__init__()
        layers = _block(3, stem, 4, 4, 0)
        for c_in, c in zip((stem,) + tuple(channels[:-1]), channels):
            layers += _block(c_in, c, 3, 2, 1)
        self.features = nn.Sequential(*layers)
        self.lin = nn.Linear(channels[-1], out)
        self.out_channels = out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.lin(self.features(x).mean(dim=(2, 3)))


def image_tensor(frames, size=CNN_SIZE) -> torch.Tensor:
    """(N, 3, H, W) uint8: the frames resized (area interpolation), cached in memory."""
    h, w = size
    out = np.zeros((len(frames), h, w, 3), np.uint8)
    for i, f in enumerate(frames):
        out[i] = per_frame(f, f"cnn{h}x{w}", lambda rgb: cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA))
    return torch.from_numpy(out).permute(0, 3, 1, 2).contiguous()


def _normalise(x: torch.Tensor) -> torch.Tensor:
    return (x.float() / 255.0 - 0.5) / 0.25


def _augment(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Random horizontal flip and colour jitter (global brightness, per-channel gain, contrast) of a float batch
    in [0, 1]."""
    n = len(x)
    flip = torch.rand(n, generator=gen) < 0.5
    x = torch.where(flip[:, None, None, None], x.flip(3), x)
    bright = 1.0 + (torch.rand(n, 1, 1, 1, generator=gen) - 0.5) * 0.4   # x0.8 .. x1.2
    gain = 1.0 + (torch.rand(n, 3, 1, 1, generator=gen) - 0.5) * 0.1     # +-5 % per channel
    contrast = 1.0 + (torch.rand(n, 1, 1, 1, generator=gen) - 0.5) * 0.4
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    return ((x - mean) * contrast + mean).mul(bright * gain).clamp(0.0, 1.0)


def cnn_embed(model: ImageEncoder, images: torch.Tensor, batch_size: int = 256) -> torch.Tensor:
    """(N, out) embeddings of a uint8 image tensor, in order (eval mode), on the CPU (the model runs on the
    device of its weights)."""
    model.eval()
    dev = next(model.parameters()).device
    with torch.inference_mode():
        out = [model(_normalise(images[s : s + batch_size].to(dev))).cpu() for s in range(0, len(images), batch_size)]
    return torch.cat(out) if out else torch.zeros((0, model.out_channels))


def image_batches(train_x: torch.Tensor, train_settings, rule: TrainingRule, batch_input):
    """The batch function (`monolib.retrieval.training.train`'s ``epoch_batches(rng, gen)``) of an encoder of
    images (or of their features) `train_x`, one row per item of `train_settings`: the paper's random triplets,
    each batch's rows (anchors, positives, negatives) turned into the model's input on the CPU by
    ``batch_input(x, gen)``, augmented with the generator `gen`."""
    settings = np.asarray(train_settings)

    def epoch_batches(rng: np.random.Generator, gen: torch.Generator):
        a, p, n = draw_triplets(settings, rng)
        return triplet_batches(a, p, n, batch_size=rule.batch_size, rng=rng, margin=rule.margin,
                               input_of=lambda idx: batch_input(train_x[torch.from_numpy(idx)], gen))

    return epoch_batches


def train_cnn(train_images: torch.Tensor, train_settings, val_images: torch.Tensor, val_settings, *,
              rule: TrainingRule, seed: int, threads: int = 2, augment: bool = True, deterministic: bool = True,
              on_epoch=None) -> TrainResult:
    """The from-scratch `ImageEncoder` on uint8 images (flip and colour jitter with `augment`), trained by `rule`
    (`monolib.retrieval.training.train`: the graph encoders' loop, schedule and model selection). `on_epoch(model)`,
    when given, adds columns to each epoch's history row (it must not draw from the seed's random streams)."""
    def batch_input(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        x = x.float() / 255.0
        if augment:
            x = _augment(x, gen)
        return (x - 0.5) / 0.25

    return training.train(ImageEncoder, image_batches(train_images, train_settings, rule, batch_input), rule=rule,
                          seed=seed, val_inputs=val_images, val_settings=val_settings, embed=cnn_embed,
                          threads=threads, deterministic=deterministic, on_epoch=on_epoch)


def image_triplet_embed(study, selection, seed: int, rule: Optional[TrainingRule] = None):
    """(test embeddings, extra, history, state) for `image_triplet`; `rule` defaults to the study's training of
    the method (`Study.gcn_spec`: `gcn:` with `image_training`)."""
    rule = rule or training_rule(study.gcn_spec("image_triplet"))
    t = time.perf_counter()
    tr, va, te = (image_tensor(fs) for fs in (selection.train, selection.val, selection.test))
    load_s = time.perf_counter() - t
    result = train_cnn(tr, [f.setting for f in selection.train], va, [f.setting for f in selection.val], rule=rule,
                       seed=seed, threads=study.threads, deterministic=study.deterministic)
    emb = cnn_embed(result.model, te).numpy().astype(np.float32)
    extra = {"best_epoch": result.best_epoch, "epochs_run": len(result.history), "train_s": result.seconds,
             "load_s": load_s, "input_size": list(CNN_SIZE), "channels": [CNN_STEM, *CNN_CHANNELS],
             "parameters": int(sum(p.numel() for p in result.model.parameters()))}
    state = {k: v.detach().cpu() for k, v in result.model.state_dict().items()}  # loadable on any machine
    return emb, extra, pd.DataFrame(result.history), state


def embed(method: str, study, selection, seed: int):
    """Embeddings of `selection.test` for an image method: (emb (N, D) float32, extra info for cell.json,
    training history DataFrame or None, model state dict or None)."""
    if method == "color_hist":
        return np.stack([per_frame(f, "color_hist", color_hist) for f in selection.test]), {}, None, None
    if method == "orb_bow":
        emb, extra, state = orb_bow_embed(selection, seed)
        return emb, extra, None, state
    if method == "image_triplet":
        return image_triplet_embed(study, selection, seed)
    raise KeyError(f"image method {method!r}: no embedding function in monolib.retrieval.baselines")


def describer(method: str, state: dict | None):
    """``describe(rgb) -> (N, D) float32``: the descriptor of `method` for a (N, H, W, 3) uint8 stack of new images
    at the study's resolution, as its cell computed the test frames' (`state`: the cell's ``model.pt``: the ORB
    vocabulary, the CNN's weights)."""
    if method == "color_hist":
        return lambda rgb: np.stack([color_hist(x) for x in rgb])
    if method == "orb_bow":
        bow = BagOfWords(state["centres"].numpy(), state["idf"].numpy())
        return lambda rgb: np.stack([bow.describe(orb_descriptors(x)) for x in rgb])
    if method == "image_triplet":
        model = ImageEncoder()
        model.load_state_dict(state)
        model.to(device())
        h, w = CNN_SIZE

        def describe(rgb: np.ndarray) -> np.ndarray:
            small = np.stack([cv2.resize(np.ascontiguousarray(x), (w, h), interpolation=cv2.INTER_AREA) for x in rgb])
            return cnn_embed(model, torch.from_numpy(small).permute(0, 3, 1, 2).contiguous()).numpy().astype(np.float32)

        return describe
    raise KeyError(f"image method {method!r}: no descriptor in monolib.retrieval.baselines")
