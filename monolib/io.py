"""File helpers shared by every stage: atomic writes, Hypersim-style HDF5, JSON, and the one figure saver."""
from __future__ import annotations

import json
import logging
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

log = logging.getLogger(__name__)


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it onto `path` only if the block succeeds.

    A run killed half-way leaves no half-written file under the final name.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give them the usual permissions
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def save_torch(path: str | os.PathLike, obj) -> None:
    """`torch.save` atomically (`atomic_path`), through a file object, so that the bytes depend on `obj` alone: given
    a path, torch names the archive inside the file after it, and the temporary name would make two saves of the
    same weights differ (and a shipped file's sha256 with them)."""
    import torch

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            torch.save(obj, f)


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | os.PathLike, obj: Any) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True, allow_nan=True) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    with open(path) as f:
        return json.load(f)


def write_h5(path: str | os.PathLike, array: np.ndarray, compression: int | None = 9) -> None:
    """One dataset named ``dataset``, gzip, no attributes: Hypersim's per-frame file format."""
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            if np.ndim(array) == 0 or compression is None:
                f.create_dataset("dataset", data=array)
            else:
                f.create_dataset("dataset", data=array, compression="gzip", compression_opts=compression)


def move_aside(folder: str | os.PathLike, kept: str | os.PathLike | None) -> None:
    """Make room in `folder` for the output of another key without deleting the output it holds: moved to `kept`
    (an older copy there, the same key's, is replaced), or removed when `kept` is None (the folder holds no
    complete output: a killed write's). Nothing happens when `folder` does not exist. Used by the cells
    (`monolib.retrieval.cell.take_over`) and the rendered settings (`monolib.data.synth`) of a shared runs folder."""
    import shutil

    folder = Path(folder)
    if not folder.exists():
        return
    if kept is None:
        shutil.rmtree(folder)
        return
    kept = Path(kept)
    if kept.exists():
        shutil.rmtree(kept)
    kept.parent.mkdir(parents=True, exist_ok=True)
    os.replace(folder, kept)


def sha256(path: str | os.PathLike) -> str:
    """The sha256 of a file's bytes (hex), read in 1 MB blocks."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class CacheUnreadable(RuntimeError):
    """A cached file that could not be read for a reason outside the file (permissions, I/O, the device): it is left
    where it is. The message names the file and the cause."""


def _outside_the_file(exc: BaseException) -> bool:
    """True for a failure that says nothing about the file's content: no right to read it, an I/O or network file
    system error, memory, or the device the reader moves a model to (CUDA out of memory, no CUDA here)."""
    import errno

    if isinstance(exc, (PermissionError, MemoryError)):
        return True
    if isinstance(exc, OSError) and exc.errno in {errno.EACCES, errno.EPERM, errno.EIO, errno.ESTALE, errno.ENOMEM,
                                                  errno.EBUSY, errno.ENOSPC, errno.ETIMEDOUT}:
        return True
    text = f"{type(exc).__name__} {exc}"
    return any(s in text for s in ("OutOfMemory", "out of memory", "CUDA", "cuda", "device-side"))


def load_cached(path: str | os.PathLike, read, what: str = "cached file") -> Any:
    """The one reader of a cached artifact (a model, a graphs file, a cell's record): ``read(path)``, or None when
    the file is absent. A file whose content cannot be read (cut short by a full disk or a killed copy, not the
    expected format, a missing key) is removed with a warning naming it, and None is returned: the caller recomputes
    it. A failure from outside the file (no permission to read it, an I/O or stale network-file-system error, the
    device out of memory) removes nothing: `CacheUnreadable` names the file and the cause. `read` should raise on
    content it does not expect (a missing key), not only on bytes it cannot parse."""
    path = Path(path)
    if not path.is_file():
        return None
    if not os.access(path, os.R_OK):
        raise CacheUnreadable(f"{path}: {what}: no permission to read it (left in place; fix its permissions or "
                              f"point the run at a runs folder of your own)")
    try:
        return read(path)
    except Exception as exc:  # torch/pickle/json/h5py each raise their own types on truncated files
        if _outside_the_file(exc):
            raise CacheUnreadable(f"{path}: {what} could not be read ({type(exc).__name__}: {str(exc)[:200]}); "
                                  f"the file is left in place") from exc
        log.warning("%s: unreadable %s (%s: %s); removed, it will be recomputed", path, what, type(exc).__name__,
                    str(exc)[:200])
        path.unlink(missing_ok=True)
        return None


def read_json_dict(path: str | os.PathLike, required: tuple[str, ...] = ()) -> dict:
    """A JSON object with the `required` keys; ValueError otherwise (for `load_cached`)."""
    obj = read_json(path)
    if not isinstance(obj, dict):
        raise ValueError(f"expected a JSON object, got {type(obj).__name__}")
    lacking = [k for k in required if k not in obj]
    if lacking:
        raise ValueError(f"no key {', '.join(lacking)}")
    return obj


class DataFileError(RuntimeError):
    """A data file is missing, unreadable or not what the format says; the message names the file."""


def read_h5(path: str | os.PathLike) -> np.ndarray:
    """The ``dataset`` of a Hypersim-style HDF5 file; one clear error naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise DataFileError(f"{path}: file not found")
    try:
        with h5py.File(path, "r") as f:
            if "dataset" not in f:
                raise DataFileError(f"{path}: no dataset named 'dataset' (found {list(f.keys())})")
            return f["dataset"][()]
    except DataFileError:
        raise
    except Exception as exc:  # h5py raises OSError and friends on truncated or foreign files
        raise DataFileError(f"{path}: not a readable HDF5 file ({exc})") from exc


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> Path:
    """Save a matplotlib figure with pinned metadata, so an unchanged figure re-saves to the same bytes."""
    import matplotlib

    path = Path(path)
    ext = path.suffix.lower()
    metadata = {".png": {"Software": None}, ".pdf": {"CreationDate": None}, ".svg": {"Date": None}}.get(ext, {})
    with matplotlib.rc_context({"svg.hashsalt": "monograph"}):
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format=ext.lstrip("."), dpi=dpi, metadata=metadata, bbox_inches="tight")
    return path
