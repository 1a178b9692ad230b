"""The dataset's digest: what `monolib verify` compares before any mean, so that a rerun says whether the data moved.

`digest(root)` hashes every file of a rendered dataset (the mini-Hypersim in the Hypersim layout) with sha256, in
the order of their paths relative to `root`, and folds the hashes into one per kind of file of each setting (the
part of a frame file's name after ``frame.NNNN.``, e.g. ``color.hdf5``, ``tonemap.jpg``; any other file by its
name), one per setting, one per file at the top level, and one for the whole. A hash folds the relative paths with
the files' hashes, so a renamed or missing file changes it as a changed byte does.

`differences(committed, fresh)` names what differs between two digests: the settings, and in each the kinds of
file (and how many files of each). A setting whose rendered files are all the same and whose marker alone differs
(``_detail/monolib_synth_setting.json``: the key of the code and library versions that rendered it) holds the
same data: `markers_only` names those, and `differences` leaves them out. The module lies outside the dataset
stage's hashed modules (`monolib.versions.STAGE_MODULES`): it reads the stage's files and never changes them.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

from monolib.io import read_json, sha256

FILE = "dataset_digest.json"   # in the study's figures folder
MARKER = "monolib_synth_setting.json"  # a setting's marker: the key it was rendered under, not data
_FRAME_FILE = re.compile(r"^frame\.\d+\.(.+)$")


def kind_of(relative: str) -> str:
    """The kind of a file: ``color.hdf5`` for ``.../frame.0003.color.hdf5``; the name of any other file."""
    name = relative.rsplit("/", 1)[-1]
    m = _FRAME_FILE.match(name)
    return m.group(1) if m else name


def _fold(pairs: list[tuple[str, str]]) -> str:
    """One sha256 over (relative path, sha256) pairs, in the order given."""
    h = hashlib.sha256()
    for rel, sha in pairs:
        h.update(f"{rel}\0{sha}\n".encode())
    return h.hexdigest()


def digest(root: str | Path) -> dict:
    """``{"algorithm", "sha256" (the whole), "files", "top" {name: sha256}, "settings" {setting: {"sha256",
    "files", "kinds" {kind: {"sha256", "files"}}}}}`` of every file under `root` (a folder per setting, files at
    the top level)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: dataset folder not found (its digest needs the rendered files)")
    files = sorted((p.relative_to(root).as_posix(), p) for p in root.rglob("*") if p.is_file())
    top: dict[str, str] = {}
    per_setting: dict[str, list[tuple[str, str]]] = {}
    for rel, p in files:
        sha = sha256(p)
        if "/" in rel:
            per_setting.setdefault(rel.split("/", 1)[0], []).append((rel, sha))
        else:
            top[rel] = sha
    settings = {}
    for name, pairs in per_setting.items():
        kinds: dict[str, list[tuple[str, str]]] = {}
        for rel, sha in pairs:
            kinds.setdefault(kind_of(rel), []).append((rel, sha))
        settings[name] = {"sha256": _fold(pairs), "files": len(pairs),
                          "kinds": {k: {"sha256": _fold(v), "files": len(v)} for k, v in sorted(kinds.items())}}
    whole = _fold(sorted(top.items()) + [(n, s["sha256"]) for n, s in sorted(settings.items())])
    return {"algorithm": "sha256", "sha256": whole, "files": len(files), "top": top, "settings": settings}


def read(path: str | Path) -> dict:
    return read_json(Path(path))


def _kind_files(kind: str, n: int) -> str:
    return f"{kind} ({n} file{'' if n == 1 else 's'})"


def differences(committed: dict, fresh: dict) -> list[str]:
    """One line per setting or top-level file that differs between two digests (none when the wholes agree)."""
    if committed.get("sha256") == fresh.get("sha256"):
        return []
    lines = []
    for name in sorted(set(committed.get("top", {})) | set(fresh.get("top", {}))):
        a, b = committed.get("top", {}).get(name), fresh.get("top", {}).get(name)
        if a != b:
            lines.append(f"{name}: " + ("missing from the fresh dataset" if b is None else
                                         "not in the committed dataset" if a is None else "differs"))
    old, new = committed.get("settings", {}), fresh.get("settings", {})
    for name in sorted(set(old) | set(new)):
        if name not in new:
            lines.append(f"setting {name}: missing from the fresh dataset")
        elif name not in old:
            lines.append(f"setting {name}: not in the committed dataset")
        elif old[name]["sha256"] != new[name]["sha256"]:
            kinds = _kinds_that_differ(old[name]["kinds"], new[name]["kinds"])
            if kinds != [MARKER]:
                kn = new[name]["kinds"]
                named = ", ".join(_kind_files(k, kn.get(k, {}).get("files", 0)) for k in kinds)
                lines.append(f"setting {name}: {named} differ")
    return lines


def _kinds_that_differ(ko: dict, kn: dict) -> list[str]:
    return [k for k in sorted(set(ko) | set(kn)) if ko.get(k, {}).get("sha256") != kn.get(k, {}).get("sha256")]


def markers_only(committed: dict, fresh: dict) -> list[str]:
    """The settings in both digests whose marker alone differs: the same rendered files, under another key."""
    old, new = committed.get("settings", {}), fresh.get("settings", {})
    return [name for name in sorted(set(old) & set(new))
            if _kinds_that_differ(old[name]["kinds"], new[name]["kinds"]) == [MARKER]]
