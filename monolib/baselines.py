"""Image-only retrieval baselines (no graph): they embed the RGB frame directly."""
from __future__ import annotations

import cv2
import numpy as np

HIST_BINS = (8, 4, 4)  # hue, saturation, value


def color_hist(rgb: np.ndarray) -> np.ndarray:
    """Global HSV colour histogram of a uint8 RGB image, L1-normalised then square-rooted (Hellinger), so that
    Euclidean distance between descriptors is a proper histogram distance."""
    hsv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2HSV)
    hist = cv2.calcHist([hsv], [0, 1, 2], None, list(HIST_BINS), [0, 180, 0, 256, 0, 256]).ravel()
    hist /= max(hist.sum(), 1.0)
    return np.sqrt(hist).astype(np.float32)
