"""The registry of retrieval methods a study can list under `methods:`.

A *graph* method trains a graph encoder on the scene graphs of a scenario; an *image* method embeds the RGB
frames directly (it ignores the scenario's depth and semantic sources and the threshold).
"""
from __future__ import annotations

# name -> (kind, description)
METHODS: dict[str, tuple[str, str]] = {
    "gcn": ("graph", "the paper's encoder as its code ran it: 5 GCNConv (128, the 5th to 64), each edge once from "
                     "the lower NYU40 id to the higher, global max pool, triplet loss"),
    "color_hist": ("image", "global HSV colour histogram, no training (calibration baseline)"),
    "orb_bow": ("image", "ORB keypoints + bag of visual words (k-means on training images), tf-idf, L2-normalised"),
    "image_triplet": ("image", "small CNN on the RGB frame, trained from scratch with the GCN's triplet loss and "
                               "budget"),
    "imagenet_gem": ("image", "ImageNet EfficientNet-Lite2's last feature map, GeM-pooled (p = 3), L2: no training"),
    "imagenet_vlad": ("image", "the same features, VLAD over a k-means vocabulary of the training split "
                               "(AnyLoc's way)"),
    "imagenet_triplet": ("image", "ImageNet EfficientNet-Lite2's head + GeM fine-tuned with the GCN's triplet loss and "
                                  "budget (trunk frozen)"),
}
# the image methods that read the ImageNet features of the frames (`monolib.perception.features`)
IMAGENET = ("imagenet_gem", "imagenet_vlad", "imagenet_triplet")


def kind(method: str, study=None) -> str:
    """'graph' or 'image'; a study's `variants:` are graph methods too."""
    if study is not None:
        return study.method_kind(method)
    return METHODS[method][0]
