"""StampMatcher: pairing by stamp without message_filters (no rclpy needed)."""

from __future__ import annotations

import pytest

from neurncd_ros.nodes.common import StampMatcher

MS = 1_000_000


def test_pairs_within_tolerance_and_drops_what_can_never_match():
    m = StampMatcher(("depth", "color"), tolerance_ns=5 * MS, capacity=10)
    assert m.add("depth", 100 * MS, "d100") is None
    assert m.add("depth", 133 * MS, "d133") is None
    # Colour 3 ms after the second depth: pairs with it, and the older depth
    # (which no later colour can match) is dropped.
    stamp, group = m.add("color", 136 * MS, "c136")
    assert stamp == 136 * MS and group == {"depth": "d133", "color": "c136"}
    assert m.dropped == 1
    assert m.add("color", 200 * MS, "c200") is None       # 6 ms off: no pair
    assert m.add("depth", 206 * MS, "d206") is None
    stamp, group = m.add("depth", 204 * MS, "d204")          # the closest one wins
    assert group == {"depth": "d204", "color": "c200"}


def test_memory_is_bounded_and_a_missing_topic_is_reported():
    m = StampMatcher(("depth", "embedding", "color"), tolerance_ns=MS, capacity=4)
    for i in range(50):
        m.add("depth", i * 33 * MS, i)
        m.add("embedding", i * 33 * MS, i)
    assert all(len(q) <= 4 for q in m._pending.values())
    assert m.dropped == 2 * (50 - 4)
    assert m.starved() == ("color",)
    stamp, group = m.add("color", 49 * 33 * MS, "c")
    assert group == {"depth": 49, "embedding": 49, "color": "c"} and m.starved() == ()


def test_unknown_slot_is_a_clear_error():
    m = StampMatcher(("depth",), tolerance_ns=MS, capacity=2)
    with pytest.raises(KeyError, match="unknown slot"):
        m.add("colour", 0, None)
