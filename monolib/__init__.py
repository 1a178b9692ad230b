"""Monograph: indoor place recognition from monocular scene graphs (a reproducible study).

Every line of logic of the study lives in this package; the notebooks in ``notebooks/`` only call into it.
"""
__version__ = "0.1.0"

import warnings as _warnings

# torch_geometric 2.8 calls torch.jit.script when imported, which torch 2.14 deprecates: without this, one
# FutureWarning about code that is not ours opens every log of the runner and every notebook's first output.
_warnings.filterwarnings("ignore", message=r"`torch\.jit\.script` is deprecated", category=FutureWarning)
# torch_geometric imports tqdm.auto, which in a notebook kernel without ipywidgets warns that it found no widgets;
# monolib's own progress lines (monolib.progress) need none.
_warnings.filterwarnings("ignore", message="IProgress not found")
