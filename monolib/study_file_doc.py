"""`docs/study-file.md`: the study file's reference, written from its schema (`monolib.params`).

One section per spec of the schema (the study's own keys, then `dataset`, `graphs`, `perception`, ... in the order a
study file holds them), each a table of its keys: type, default, allowed choices or bounds, and the key's one line
of meaning (its `Field(description=...)`). `make study-file-doc` rewrites the page; `tests/test_params.py` checks
that the committed page is what the schema writes.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import re
import textwrap
import typing
from pathlib import Path
from typing import Any, Literal

from monolib import io, params, paths

PAGE = paths.ROOT / "docs" / "study-file.md"
WIDTH = 120  # prose lines of the page

INTRO = """\
A study is one YAML file in `params/` (`monolib study <name>`). Each section below is one part of the file: its
keys, each key's type, its default (in YAML; `{}`: an entry whose keys all keep their defaults), the values it
allows, and what it means. A key left out takes its default; a study that `extends:` another takes the other
file's values as its defaults (mappings merged key by key, a mapping set to null removed).

When a study is loaded (`monolib.params.load_study`), the file is checked against this schema before any work
starts: an unknown key, a wrong type, a value outside its choices or bounds, a broken rule between keys (the
meanings below name them) or a file it names that is not there is one `StudyError` naming the file, the key,
what was expected and the value given, such as `params/quick.yaml: dataset.width: expected 16..1024, got 2000`.

This page is written from the schema in `monolib/params.py` by `make study-file-doc`; a test checks that it is
current."""


def sections(spec=params.Study, where: str = "") -> list[tuple[str, Any]]:
    """``(key, spec)`` of `spec` and of every spec below it, depth first in the order of their keys: ``("",
    Study)``, ``("dataset", DatasetSpec)``, ..., ``("perception.depth[i]", DepthSpec)``, ``("scenarios.<name>",
    Scenario)``."""
    out = [(where, spec)]
    hints = typing.get_type_hints(spec, include_extras=True)
    for name in params.study_keys(spec):
        tp, _ = params.unwrap(hints[name])
        key = f"{where}.{name}" if where else name
        if typing.get_origin(tp) is list:
            tp, key = params.unwrap(typing.get_args(tp)[0])[0], f"{key}[i]"
        elif typing.get_origin(tp) is dict:
            tp, key = params.unwrap(typing.get_args(tp)[1])[0], f"{key}.<name>"
        if dataclasses.is_dataclass(tp):
            out += sections(tp, key)
    return out


def title(key: str) -> str:
    """A section's heading: the key of its spec in the file."""
    return f"`{key}`" if key else "Top-level keys"


def anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _nullable(tp) -> bool:
    while typing.get_origin(tp) is typing.Annotated:
        tp = tp.__origin__
    return typing.get_origin(tp) is typing.Union and type(None) in typing.get_args(tp)


def type_name(tp, links: dict, plural: bool = False) -> str:
    """A declared type in words: ``integer``, ``list of numbers``, ``mapping of names to [scenarios.<name>]``, a
    spec as a link to its section; ``or null`` where the key may be null."""
    base, _ = params.unwrap(tp)
    s = "s" if plural else ""
    if dataclasses.is_dataclass(base):
        key = links[base]
        words = f"[{title(key)}](#{anchor(title(key))})" + (" entries" if plural else "")
    elif typing.get_origin(base) is list:
        words = f"list{s} of {type_name(typing.get_args(base)[0], links, plural=True)}"
    elif typing.get_origin(base) is dict:
        words = f"mapping{s} of names to {type_name(typing.get_args(base)[1], links, plural=True)}"
    elif base is dict:
        words = f"mapping{s}"
    elif typing.get_origin(base) is Literal:
        words = f"string{s}"
    else:
        words = {int: "integer", float: "number", bool: "true / false", str: "string"}[base] + s
    return f"{words} or null" if _nullable(tp) else words


def yaml_value(value: Any) -> str:
    """`value` as YAML writes it in flow style; a spec as its keys that differ from their defaults."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float) and math.isinf(value):
        return ".inf" if value > 0 else "-.inf"
    if isinstance(value, str):
        return value if value else '""'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k}: {yaml_value(v)}" for k, v in value.items()) + "}"
    if dataclasses.is_dataclass(value):
        base = type(value)()
        return yaml_value({f.name: getattr(value, f.name) for f in dataclasses.fields(value)
                           if getattr(value, f.name) != getattr(base, f.name)})
    return repr(value)


def default_of(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        return f"`{yaml_value(f.default)}`"
    if f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
        return "its keys' defaults" if dataclasses.is_dataclass(value) else f"`{yaml_value(value)}`"
    return "(required)"


def _constraints(meta: list) -> list[str]:
    b = {name: getattr(m, name) for m in meta for name in ("ge", "gt", "le", "lt", "min_length") if hasattr(m, name)}
    if "ge" in b and "le" in b:
        return [f"{b['ge']:g} .. {b['le']:g}"]
    words = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}
    out = [f"{words[k]} {v:g}" for k, v in b.items() if k in words]
    return out + (["non-empty"] if b.get("min_length") else [])


def allowed(tp) -> str:
    """A key's choices (a `Literal`'s values) or bounds, and those of each item of a list."""
    base, meta = params.unwrap(tp)
    out = _constraints(meta)
    if typing.get_origin(base) is Literal:
        out.append(", ".join(map(str, typing.get_args(base))))
    elif typing.get_origin(base) is list:
        item = allowed(typing.get_args(base)[0])
        out += [f"each {item}"] if item else []
    return "; ".join(out)


def cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def table(spec, links: dict) -> list[str]:
    """The table of `spec`'s keys."""
    hints = typing.get_type_hints(spec, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(spec)}
    rows = ["| key | type | default | choices / bounds | meaning |", "| --- | --- | --- | --- | --- |"]
    for name in params.study_keys(spec):
        tp = hints[name]
        meaning = spec.__pydantic_fields__[name].description
        rows.append("| " + " | ".join(cell(c) for c in (f"`{name}`", type_name(tp, links), default_of(fields[name]),
                                                          allowed(tp), meaning)) + " |")
    return rows


def _prose(text: str) -> str:
    """A docstring as paragraphs of lines at most `WIDTH` long."""
    paragraphs = inspect.cleandoc(text).split("\n\n")
    return "\n\n".join(textwrap.fill(" ".join(p.split()), WIDTH) for p in paragraphs)


def reference() -> str:
    """The text of `docs/study-file.md`."""
    found = sections()
    links = {spec: key for key, spec in reversed(found)}
    out = ["# The study file", "", INTRO]
    for key, spec in found:
        out += ["", f"## {title(key)}", "", _prose(spec.__doc__), ""] + table(spec, links)
    return "\n".join(out) + "\n"


def write(path: Path = PAGE) -> bool:
    """Rewrite `path` from the schema; True when it changed."""
    text = reference()
    if path.is_file() and path.read_text() == text:
        return False
    io.write_text(path, text)
    return True
