"""Progress a person can watch, on a terminal and in a log file.

`tqdm(...)` takes tqdm's arguments (an iterable or `total`, `desc`, `unit`, `disable`, `leave`) and is what every
module of monolib imports instead of `tqdm.auto.tqdm`:

- on a terminal (stderr is a TTY) it is tqdm's bar, redrawn in place;
- anywhere else (`make study > log 2>&1`, a pipe, a notebook kernel, CI) it prints plain lines to stderr: one when
  the loop starts, one at a new tenth of the way when `EVERY_SECONDS` have passed since the last line, and one at
  the end with the elapsed time, so that a log reads as a few lines per stage instead of thousands of
  carriage-return redraws. A transient loop (`leave=False`: the batches of one epoch, the frames read before
  training) prints only when it runs longer than `QUIET_SECONDS`: the line of the stage around it already says
  that it ran.

`MONOLIB_PROGRESS=bar|lines|off` overrides the choice (`off`: no progress output at all).
"""
from __future__ import annotations

import os
import sys
from time import perf_counter as _clock
from typing import Any, Iterable, Optional

QUIET_SECONDS = 30.0
EVERY_SECONDS = 5.0
STEPS = 10  # at most one line per tenth of the way


def mode() -> str:
    """'bar', 'lines' or 'off': `MONOLIB_PROGRESS` when set, else 'bar' on a terminal and 'lines' elsewhere."""
    chosen = os.environ.get("MONOLIB_PROGRESS", "").strip().lower()
    if chosen in ("bar", "lines", "off"):
        return chosen
    try:
        return "bar" if sys.stderr.isatty() else "lines"
    except (AttributeError, ValueError):  # a closed or replaced stream
        return "lines"


def tqdm(iterable: Optional[Iterable] = None, *args: Any, **kwargs: Any):
    """tqdm's bar on a terminal, `Lines` elsewhere (see the module's docstring)."""
    chosen = mode()
    if chosen == "bar":
        from tqdm.auto import tqdm as bar

        return bar(iterable, *args, **kwargs)
    if chosen == "off":
        kwargs["disable"] = True
    return Lines(iterable, *args, **kwargs)


def _seconds(s: float) -> str:
    return f"{s:.0f} s" if s >= 10 else f"{s:.1f} s"


class Lines:
    """The part of tqdm's interface that monolib uses (iteration, `update`, `set_postfix`, `close`, a context
    manager), printing at most `STEPS` + 1 plain lines per loop."""

    def __init__(self, iterable: Optional[Iterable] = None, desc: Optional[str] = None, total: Optional[float] = None,
                 leave: bool = True, file=None, disable: bool = False, unit: str = "it", **_ignored: Any):
        if total is None and iterable is not None:
            try:
                total = len(iterable)  # type: ignore[arg-type]
            except TypeError:
                total = None
        self.iterable, self.desc, self.total, self.unit = iterable, desc or "progress", total, unit
        self.leave, self.file = leave, file
        self.disable = disable or total == 0  # nothing to do: nothing to say
        self.n = 0
        self.postfix = ""
        self._t0 = self._last = _clock()
        self._step = 0  # tenths already reported
        self._printed = False
        self._closed = False
        if not self.disable and self.leave:
            todo = f"{self.total:g} {self.unit}" if self.total is not None else "started"
            self._line(f"{todo}" if self.total is None else f"0/{todo}")

    def _line(self, text: str) -> None:
        out = self.file or sys.stderr
        suffix = f" ({self.postfix})" if self.postfix else ""
        print(f"{self.desc}: {text}{suffix}", file=out, flush=True)
        self._printed = True
        self._last = _clock()

    def __iter__(self):
        if self.iterable is None:
            raise TypeError("Lines: nothing to iterate over")
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __len__(self) -> int:
        return int(self.total or 0)

    def __enter__(self) -> "Lines":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def update(self, n: float = 1) -> None:
        self.n += n
        if self.disable or not self.total:
            return
        step = min(STEPS, int(STEPS * self.n / self.total))
        if step <= self._step or step >= STEPS:  # the last tenth is the closing line
            return
        now = _clock()
        if now - self._last < EVERY_SECONDS:
            return
        self._step = step
        elapsed = now - self._t0
        if self.leave or elapsed >= QUIET_SECONDS:
            self._line(f"{self.n:g}/{self.total:g} {self.unit} ({100 * self.n / self.total:.0f}%, {_seconds(elapsed)})")

    def set_postfix(self, ordered_dict: Optional[dict] = None, refresh: bool = True, **kwargs: Any) -> None:
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def set_description(self, desc: Optional[str] = None, refresh: bool = True) -> None:
        self.desc = desc or self.desc

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self.disable or not (self.leave or self._printed):
            return
        total = f"/{self.total:g}" if self.total is not None else ""
        self._line(f"{self.n:g}{total} {self.unit} done in {_seconds(_clock() - self._t0)}")
