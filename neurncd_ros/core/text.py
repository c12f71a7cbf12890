"""Small helpers for the lines people read (summaries of the offline tools)."""

from __future__ import annotations

import re
import sys
import time
from contextlib import contextmanager
from typing import Any, Callable, Iterator, TextIO


def plural(n: int, word: str) -> str:
    """``"1 frame"``, ``"2 frames"``: a count with its noun (regular plurals only)."""
    return f"{n} {word}" + ("" if n == 1 else "s")


class ProgressLines:
    """A text stream for stderr when it is a file or a pipe: progress bars as lines.

    tqdm redraws a bar in place with carriage returns (and moves between nested bars with
    cursor codes): in a log file that is one endless line, with the next message glued to
    the bar. Through this stream each bar state becomes a line of its own, at most one per
    ``interval`` seconds per bar plus its final one (n/n; for a bar without a total, whose
    text cannot say it is final, the state before the newline tqdm ends a closed bar
    with); a bar's clearing is dropped and other text passes through unchanged. (A bar
    without a total with other bars nested below it would show a line per inner redraw,
    as tqdm's move down to them is that newline too; no command nests one.)"""

    _CODES = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
    _DONE = re.compile(r"(\S+)/(\S+) \[")
    _NAME = re.compile(r"(.*?):\s+\d+%")

    def __init__(self, stream: TextIO, interval: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream
        self.interval = interval
        self.clock = clock
        self.last: dict[str, float] = {}  # per bar (its description): when last shown
        self.shown = ""  # the last bar line shown, without its times
        self.after_bar = False  # the last write was tqdm's (a bar, its clearing, a move)
        self.pending = ""  # the last state of a bar without a total, not shown

    def write(self, text: str) -> int:
        if "\r" not in text and "\x1b[" not in text:
            if self.after_bar and not text.strip("\n"):
                if self.pending and "\n" in text:  # a bar without a total closed
                    self.stream.write(self.pending + "\n")
                    self.shown, self.pending = self.pending.rsplit(" [", 1)[0], ""
                return len(text)  # a move down to a nested bar's line
            self.after_bar, self.shown, self.pending = False, "", ""
            return self.stream.write(text)
        self.after_bar = True
        for part in re.split(r"[\r\n]", self._CODES.sub("", text)):
            part = part.rstrip()
            if part:
                self._bar(part)
        return len(text)

    def _bar(self, state: str) -> None:
        named = self._NAME.match(state)
        name = named.group(1) if named else state.split(":")[0]
        count = state.rsplit(" [", 1)[0]  # the bar without its times and rate
        if count == self.shown:  # the line just shown drawn again (closing its bar)
            return
        done = self._DONE.search(state)
        now = self.clock()
        if (done and done.group(1) == done.group(2)) or \
                now - self.last.get(name, -float("inf")) >= self.interval:
            self.last[name], self.shown, self.pending = now, count, ""
            self.stream.write(state + "\n")
        elif done is None:
            self.pending = state

    def isatty(self) -> bool:
        return False

    def __getattr__(self, name: str) -> Any:  # flush, fileno, encoding ... of the stream
        return getattr(self.stream, name)


@contextmanager
def progress_as_lines(interval: float = 10.0) -> Iterator[None]:
    """Within it, where stderr is not a terminal, progress bars show on it as lines
    (:class:`ProgressLines`): for the entry points (neurncd, the benchmarks), which own
    stderr; ``sys.stderr`` is itself again after it."""
    saved = sys.stderr
    if not saved.isatty() and not isinstance(saved, ProgressLines):
        sys.stderr = ProgressLines(saved, interval)
    try:
        yield
    finally:
        sys.stderr = saved
