"""Progress bars of ``neurncd eval``: one per stage and bag, on stderr as the engine's.

An eval spends most of its time after the engine pass (the ablation's discovery
re-runs, the explicit map, a Semantic-NeRF field per label fraction, each tens of
seconds per bag): every stage gets its own bar, named by the stage and the bag
(``semnerf 1% [scene2.mcap]``), so a long wait says what it is waiting on."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Iterable

if TYPE_CHECKING:
    from tqdm import tqdm


def label(stage: str, name: str = "") -> str:
    """A bar's description: the stage, then the bag's file name in brackets."""
    short = (Path(name).name or name) if name else ""
    return f"{stage} [{short}]" if short else stage


def bar(total: int | None, stage: str, name: str = "", enabled: bool = True,
        iterable: Iterable | None = None, unit: str = "frame") -> tqdm:
    """A tqdm bar on stderr for ``stage`` of bag ``name`` (a disabled one, which only
    counts, when ``enabled`` is false); wraps ``iterable`` when given."""
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=label(stage, name), unit=unit,
                disable=not enabled)


def tick(b: tqdm | None, n: int = 1, **postfix) -> None:
    """Advance bar ``b`` (None: no bar) by ``n`` and show ``postfix`` beside it."""
    if b is None:
        return
    if postfix:
        b.set_postfix(postfix, refresh=False)
    b.update(n)
