"""Monograph: indoor place recognition from monocular scene graphs (a reproducible study).

Every line of logic of the study lives in this package; the notebooks in ``notebooks/`` only call into it.
"""
__version__ = "0.1.0"
