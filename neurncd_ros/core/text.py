"""Small helpers for the lines people read (summaries of the offline tools)."""

from __future__ import annotations


def plural(n: int, word: str) -> str:
    """``"1 frame"``, ``"2 frames"``: a count with its noun (regular plurals only)."""
    return f"{n} {word}" + ("" if n == 1 else "s")
