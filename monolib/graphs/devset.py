"""The development set of the published graphs (18 of the release's 24 volumes, its ``train/`` files only) put
where a study reads it: `unpack` checks an archive or folder and writes it into an ignored folder in one step.
Kept out of `monolib.graphs.published` (whose code is part of the graph stage's cache key): unpacking decides no
number."""
from __future__ import annotations

import hashlib
import shutil
import tarfile
import tempfile
from pathlib import Path

from monolib.graphs.published import FILE_RE, PublishedGraphError, read_file

DEV_FOLDER = "published_graphs_dev"  # the top folder of the development set's archive


def unpack(source: str | Path, out: str | Path) -> Path:
    """The development set of the published graphs (`source`: its ``.tar.xz`` archive, or a folder holding
    ``train/``) into `out` (``out/train/ai_VVV_NNN_XX_graphs.pt`` and the archive's ``SOURCE.md``), checked before
    anything is in place: every member a plain file under the archive's top folder with a release name, every graph
    file parsed by `read_file`. Written into a temporary folder beside `out` and renamed onto it, so that a damaged
    or missing source leaves `out` as it was. Returns `out`. Raises `PublishedGraphError` naming the source and what
    was wrong. A source whose files are all in `out` already, byte for byte, is not written again."""
    source, out = Path(source), Path(out)
    if not source.exists():
        raise PublishedGraphError(f"{source}: not found; expected the development set's archive "
                                  f"({DEV_FOLDER}.tar.xz) or a folder with its train/ folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}-", dir=out.parent))
    try:
        if source.is_dir():
            if not (source / "train").is_dir():
                raise PublishedGraphError(f"{source}: no train/ folder; expected a folder of the release's layout "
                                          f"(train/ai_VVV_NNN_XX_graphs.pt)")
            shutil.copytree(source / "train", tmp / "train")
            if (source / "SOURCE.md").is_file():
                shutil.copy2(source / "SOURCE.md", tmp / "SOURCE.md")
        else:
            try:
                with tarfile.open(source, "r:*") as tar:
                    members = tar.getmembers()
                    for m in members:
                        parts = Path(m.name).parts
                        if not parts or parts[0] != DEV_FOLDER or ".." in parts or Path(m.name).is_absolute():
                            raise PublishedGraphError(f"{source}: member {m.name!r} is outside {DEV_FOLDER}/; "
                                                      f"expected the development set's archive")
                        if not (m.isfile() or m.isdir()):
                            raise PublishedGraphError(f"{source}: member {m.name!r} is not a plain file or folder")
                        if m.isfile() and parts[1:2] == ("train",) and not FILE_RE.match(parts[-1]):
                            raise PublishedGraphError(f"{source}: member {m.name!r}: expected train/ files named "
                                                      f"ai_VVV_NNN_XX_graphs.pt")
                    tar.extractall(tmp, members=members, filter="data")
            except (tarfile.TarError, EOFError, OSError) as exc:
                raise PublishedGraphError(f"{source}: not a readable .tar.xz archive ({exc})") from None
            if not (tmp / DEV_FOLDER / "train").is_dir():
                raise PublishedGraphError(f"{source}: no {DEV_FOLDER}/train/ folder in the archive")
            for item in (tmp / DEV_FOLDER).iterdir():
                item.rename(tmp / item.name)
            (tmp / DEV_FOLDER).rmdir()
        files = sorted((tmp / "train").glob("*_graphs.pt"))
        if not files:
            raise PublishedGraphError(f"{source}: no ai_VVV_NNN_XX_graphs.pt files in train/")
        for p in files:
            try:
                read_file(p)
            except PublishedGraphError as exc:
                raise PublishedGraphError(f"{source}: {p.name}: {str(exc).split(': ', 1)[-1]}") from None

        def digest(folder: Path) -> dict[str, str]:
            return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((folder / "train").glob("*"))}

        if out.is_dir() and (out / "train").is_dir() and digest(out) == digest(tmp):
            return out
        old = out.with_name(f".{out.name}-old")
        if out.exists():
            shutil.rmtree(old, ignore_errors=True)
            out.rename(old)
        tmp.rename(out)
        shutil.rmtree(old, ignore_errors=True)
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
