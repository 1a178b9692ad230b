"""Which test settings each protocol takes (``paper``, ``siblings``), by name only: read by frame selection
(`monolib.data.selection`, `monolib.graphs.published`) and by the retrieval stage (`monolib.retrieval.evaluate`), which
sit on both sides of it. A setting's family is the ``ai_VVV`` part of its name (a Hypersim volume).
"""
from __future__ import annotations

from monolib.params import PAPER, SIBLINGS, Protocol


class ProtocolDataError(ValueError):
    """The test data cannot provide a protocol (too few families, a family without a sibling, too few frames)."""


def family(setting: str) -> str:
    """The family of a setting: the ``ai_VVV`` part of ``ai_VVV_NNN`` (a Hypersim volume)."""
    parts = str(setting).split("_")
    return "_".join(parts[:2]) if len(parts) >= 3 else str(setting)


def protocol_settings(settings, protocol: Protocol, where: str = "test split") -> dict[str, list[str]]:
    """``{protocol: its settings (sorted)}`` chosen from `settings` (the test settings that hold enough frames).

    ``paper``: the first setting (sorted by name) of each of the first `protocol.settings` families (sorted), so
    every setting is of another family; with ``protocol.families`` false (real data), `protocol.settings` settings
    taken in turn from each family (the first of each family in name order, then the second of each, ...), which
    is the same choice wherever there are enough families. ``siblings`` (when `protocol.siblings` > 0): the first
    `protocol.siblings` families (sorted) holding at least 2 of the settings, their first two settings each. The rule
    only reads names, and applied to the union of its own result it gives that result again (what a cell sees). Raises
    `ProtocolDataError` naming what is missing."""
    names = sorted(set(map(str, settings)))
    fams: dict[str, list[str]] = {}
    for n in names:
        fams.setdefault(family(n), []).append(n)
    out: dict[str, list[str]] = {}
    if protocol.families is False:
        if len(names) < protocol.settings:
            raise ProtocolDataError(
                f"{where}: the paper protocol needs {protocol.settings} test settings with >= {protocol.frames} frames "
                f"(protocol.settings); found {len(names)} ({', '.join(names) or 'none'})")
        # in turn from each family: the first setting of each family (sorted), then the second of each, ...
        turns = sorted((i, f, n) for f in fams for i, n in enumerate(fams[f]))
        out[PAPER] = sorted(n for _, _, n in turns[: protocol.settings])
    elif len(fams) < protocol.settings:
        raise ProtocolDataError(
            f"{where}: the paper protocol needs {protocol.settings} test settings of different families (ai_VVV) "
            f"with >= {protocol.frames} frames (protocol.settings; protocol.families: false takes them in turn from "
            f"fewer families); found {len(fams)} families among {len(names)} such settings "
            f"({', '.join(sorted(fams)) or 'none'})")
    else:
        out[PAPER] = sorted(fams[f][0] for f in sorted(fams)[: protocol.settings])
    if protocol.siblings > 0:
        pairs = [f for f in sorted(fams) if len(fams[f]) >= 2]
        if len(pairs) < protocol.siblings:
            single = [f for f in sorted(fams) if len(fams[f]) < 2]
            raise ProtocolDataError(
                f"{where}: the siblings protocol needs {protocol.siblings} families (ai_VVV) with 2 test settings of "
                f">= {protocol.frames} frames each (protocol.siblings); found {len(pairs)} "
                f"({', '.join(pairs) or 'none'}); families without a sibling: {', '.join(single) or 'none'}")
        out[SIBLINGS] = sorted(n for f in pairs[: protocol.siblings] for n in fams[f][:2])
    return out
