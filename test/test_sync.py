"""StampSync: pairing by stamp without message_filters, bounded whatever arrives."""

from __future__ import annotations

import numpy as np
import pytest

from neurncd_ros.core import sync

from fakeclock import MS, Clock  # noqa: E402,F401


def test_pairs_nearest_within_tolerance_and_supersedes_what_can_never_pair():
    s = sync.StampSync(("depth", "color"), tolerance_ns=5 * MS, capacity=10)
    assert s.add("depth", 100 * MS, "d100") == []
    assert s.add("depth", 133 * MS, "d133") == []
    # Colour 3 ms after the second depth pairs with it; the older depth can never pair now.
    assert s.add("color", 136 * MS, "c136") == [(133 * MS, {"depth": "d133", "color": "c136"})]
    assert s.drops["superseded"] == 1 and s.pending() == 0
    assert s.add("color", 200 * MS, "c200") == []           # no depth yet
    assert s.add("depth", 206 * MS, "d206") == []           # 6 ms off: no pair
    got = s.add("depth", 204 * MS, "d204")                   # within 5 ms: pairs
    assert got == [(204 * MS, {"depth": "d204", "color": "c200"})]
    assert s.groups == 2


def test_group_stamp_is_the_reference_streams():
    s = sync.StampSync(("embedding", "color", "pose"), tolerance_ns=20 * MS)
    s.add("color", 1000 * MS, "c")
    s.add("pose", 1010 * MS, "p")
    assert s.add("embedding", 1000 * MS, "e") == [(1000 * MS, {"embedding": "e", "color": "c",
                                                               "pose": "p"})]


def test_duplicates_and_out_of_order_stamps_are_dropped_by_reason():
    s = sync.StampSync(("depth", "color"), tolerance_ns=MS, reset_after=3)
    s.add("depth", 100 * MS, "a")
    assert s.add("depth", 100 * MS, "again") == []
    assert s.drops["duplicate"] == 1
    assert s.add("color", 100 * MS, "c")[0][1]["depth"] == "a"
    assert s.add("depth", 50 * MS, "late") == []            # older than a paired frame
    # Held until it is clear the timeline did not restart: the next frame on it says so.
    s.add("depth", 133 * MS, "b")
    assert s.drops["out_of_order"] == 1
    assert s.add("color", 133 * MS, "c2")[0][0] == 133 * MS  # later frames still pair


def test_a_timeline_that_keeps_going_back_restarts_the_pairing():
    """A bag replayed in a loop starts its stamps again: after reset_after such messages
    the pairing follows the new timeline instead of dropping everything forever."""
    s = sync.StampSync(("depth", "color"), tolerance_ns=MS, reset_after=4)
    for k in range(10):
        s.add("depth", (1000 + k) * MS, k)
        s.add("color", (1000 + k) * MS, k)
    assert s.groups == 10
    groups = []
    for k in range(10):
        groups += s.add("depth", (10 + k) * MS, k)
        groups += s.add("color", (10 + k) * MS, k)
    # The messages that went back before the restart was clear are paired on the new
    # timeline, not lost (a bag played again into running nodes lost its first views).
    assert s.resets == 1 and s.drops["out_of_order"] == 0
    assert [g[0] for g in groups] == [(10 + k) * MS for k in range(10)]


def test_one_far_future_stamp_is_dropped_and_the_timeline_goes_on():
    """A driver's glitch stamps one frame 10^6 s ahead: it is dropped as a jump and
    reported, and the good frames after it pair as before (it does not become the
    timeline that every later frame would be older than)."""
    seen = []
    s = sync.StampSync(("depth", "color"), tolerance_ns=MS, reset_after=4,
                       max_jump_ns=30_000 * MS, on_anomaly=lambda *a: seen.append(a))
    for k in range(5):
        s.add("depth", (1000 + 33 * k) * MS, k)
        s.add("color", (1000 + 33 * k) * MS, k)
    bad = (1000 + 10**9) * MS
    assert s.add("depth", bad, "bad") == [] and s.add("color", bad, "bad") == []
    groups = []
    for k in range(5, 10):
        groups += s.add("depth", (1000 + 33 * k) * MS, k)
        groups += s.add("color", (1000 + 33 * k) * MS, k)
    # Dropped and reported as jumps once the next good frame shows the timeline went on.
    assert s.drops["jump"] == 2 and s.resets == 0
    assert seen[0][:3] == ("depth", "jump", bad) and seen[0][3].endswith(" s")
    assert [g[1]["depth"] for g in groups] == [5, 6, 7, 8, 9]
    assert s.drops["out_of_order"] == 0


def test_a_stream_that_paused_is_on_time_and_a_glitch_after_it_is_not():
    """A live camera stops for 44 s and resumes: its stamps moved on with the clock, so
    its first frames pair (no jump); a stamp far beyond the pause is still a jump."""
    clock, seen = Clock(), []
    s = sync.StampSync(("depth", "color"), tolerance_ns=MS, horizon_s=1000.0,
                       max_jump_ns=30_000 * MS, clock=clock,
                       on_anomaly=lambda *a: seen.append(a[1]))
    s.add("depth", 0, 0)
    s.add("color", 0, 0)
    clock.t = 44.0
    assert s.add("depth", 44_000 * MS, 1) == [] and s.add("color", 44_000 * MS, 1) == \
        [(44_000 * MS, {"depth": 1, "color": 1})]
    assert "jump" not in seen and s.drops["jump"] == 0
    clock.t = 45.0
    assert s.add("depth", (45_000 + 31_000) * MS, 2) == []
    s.add("depth", 45_000 * MS, 3)  # the timeline goes on: the far stamp was a glitch
    assert seen == ["jump"] and s.drops["jump"] == 1


def test_stamps_that_keep_jumping_ahead_restart_the_pairing():
    """A new bag (or a camera restarted after a long pause) jumps ahead for good: after
    reset_after such messages the pairing follows the new timeline."""
    s = sync.StampSync(("depth", "color"), tolerance_ns=MS, reset_after=4,
                       max_jump_ns=30_000 * MS)
    s.add("depth", 0, 0)
    s.add("color", 0, 0)
    groups = []
    for k in range(6):
        groups += s.add("depth", (100_000 + 33 * k) * MS, k)
        groups += s.add("color", (100_000 + 33 * k) * MS, k)
    assert s.resets == 1 and s.drops["jump"] == 0
    assert [g[1]["depth"] for g in groups] == [0, 1, 2, 3, 4, 5]  # none lost
    unlimited = sync.StampSync(("depth",), tolerance_ns=MS)  # max_jump_ns 0: no limit
    unlimited.add("depth", 0, 0)
    assert unlimited.add("depth", 10**18, 1) == [(10**18, {"depth": 1})]


def test_a_reference_message_given_up_unpaired_names_the_missing_streams():
    """After the streams have paired once, a frame whose pose never comes is reported
    with the stream it waited for, when it expires and when a newer frame pairs first;
    before the first group (partners sent before the node subscribed) nothing is
    reported."""
    clock = Clock()
    seen = []
    s = sync.StampSync(("embedding", "color", "pose"), tolerance_ns=MS, horizon_s=1.0,
                       clock=clock, on_anomaly=lambda *a: seen.append(a))
    s.add("embedding", 0, "e0")                             # its partners never come
    clock.t = 2.0
    s.add("color", 100 * MS, "c1")
    s.add("pose", 100 * MS, "p1")
    assert s.add("embedding", 100 * MS, "e1")[0][0] == 100 * MS
    assert seen == [] and s.drops["expired"] == 1
    s.add("embedding", 200 * MS, "e2")
    s.add("color", 200 * MS, "c2")                          # no pose for this frame
    clock.t = 4.0
    s.add("color", 300 * MS, "c3")
    assert seen == [("embedding", "unpaired", 200 * MS, "pose")]
    # In a continuous stream the frame is given up as soon as a newer one pairs.
    seen.clear()
    s.add("embedding", 300 * MS, "e3")                      # colour c3 came; no pose
    for k in (4, 5):
        for stream in ("embedding", "color", "pose"):
            s.add(stream, k * 100 * MS, f"{stream}{k}")
    assert seen == [("embedding", "unpaired", 300 * MS, "pose")]


def test_inputs_whose_stamps_never_agree_are_reported_before_any_pair():
    """A pose stamped 50 ms after its frame (stamped when it was computed), at 20 ms
    tolerance: nothing ever pairs, and the node said nothing at all (the reports waited
    for a first group). Each embedding that expires while the pose does arrive is reported
    as ``apart``, with the offset of the nearest pose (also when that pose expired
    first); one whose partners come late (a backbone seconds behind) as ``late``; at a
    start whose first partners predate the subscription, still nothing."""
    clock = Clock()
    seen = []
    s = sync.StampSync(("embedding", "color", "pose"), tolerance_ns=20 * MS, horizon_s=1.0,
                       clock=clock, on_anomaly=lambda *a: seen.append(a))
    for k in range(12):                                     # 6 Hz, pose 50 ms after
        clock.t = k / 6
        s.add("pose", k * 166 * MS + 50 * MS, f"p{k}")
        s.add("color", k * 166 * MS, f"c{k}")
        assert s.add("embedding", k * 166 * MS, f"e{k}") == []
    assert s.groups == 0 and seen, "frames that never pair are reported"
    assert {a[:2] for a in seen} == {("embedding", "apart")}
    assert seen[0][2] == 0
    assert seen[0][3] == "the nearest pose is stamped 50.0 ms after it (sync tolerance 20 ms)"
    # Partners that come, but seconds before their embedding: late, not apart.
    seen.clear()
    slow = sync.StampSync(("embedding", "color"), tolerance_ns=MS, horizon_s=1.0,
                          clock=clock, on_anomaly=lambda *a: seen.append(a))
    clock.t = 10.0
    slow.add("color", 0, "c0")
    clock.t = 11.5                                          # c0 expires on this add
    slow.add("embedding", 0, "e0")
    clock.t = 13.0
    slow.add("color", 100 * MS, "c1")                       # e0 expires in its turn
    assert seen == [("embedding", "late", 0, "color (1.5 s before it)")]
    # A healthy start: the first colour predates the subscription; the next pair supersedes
    # the lone embedding before it could expire: nothing to report.
    seen.clear()
    start = sync.StampSync(("embedding", "color"), tolerance_ns=MS, horizon_s=1.0,
                           clock=clock, on_anomaly=lambda *a: seen.append(a))
    start.add("embedding", 0, "e0")
    start.add("color", 100 * MS, "c1")
    assert start.add("embedding", 100 * MS, "e1")[0][0] == 100 * MS
    assert seen == []


def test_a_reference_message_after_its_partners_expired_is_reported_late():
    """An embedding that comes after its colour and pose waited the horizon and expired
    (a backbone seconds behind) is reported as late, with how far behind, not as a frame
    whose partners never came; a partner that never came is still named as missing."""
    clock = Clock()
    seen = []
    s = sync.StampSync(("embedding", "color", "pose"), tolerance_ns=MS, horizon_s=1.0,
                       clock=clock, on_anomaly=lambda *a: seen.append(a))
    for stream in ("embedding", "color", "pose"):
        s.add(stream, 0, stream)                            # one group: reports are on
    s.add("color", 100 * MS, "c1")
    s.add("pose", 100 * MS, "p1")
    clock.t = 2.5                                            # they expire meanwhile
    assert s.add("embedding", 100 * MS, "e1") == []
    clock.t = 4.0
    s.add("color", 200 * MS, "c2")                           # e1 expires in its turn
    assert seen == [("embedding", "late", 100 * MS, "color, pose (2.5 s before it)")]
    assert s.drops["expired"] == 3
    # Colour came and expired, the pose never came: the missing pose is what is named.
    seen.clear()
    s.add("color", 300 * MS, "c3")
    clock.t = 6.0
    s.add("embedding", 300 * MS, "e3")
    clock.t = 8.0
    s.add("color", 400 * MS, "c4")
    assert seen == [("embedding", "unpaired", 300 * MS, "pose")]
    # Pushed out of a full queue before the embedding came: late too.
    seen.clear()
    small = sync.StampSync(("embedding", "color"), tolerance_ns=MS, horizon_s=10.0,
                           capacity=2, clock=clock, on_anomaly=lambda *a: seen.append(a))
    small.add("color", 0, "c0")
    small.add("embedding", 0, "e0")
    for k in (1, 2, 3):
        small.add("color", k * 100 * MS, f"c{k}")           # c1 is pushed out by c3
    assert small.drops["overflow"] == 1
    small.add("embedding", 100 * MS, "e1")
    small.add("embedding", 200 * MS, "e2")                   # pairs; e1 is given up
    assert seen == [("embedding", "late", 100 * MS, "color (0.0 s before it)")]
    # After a reset (a new bag) the old expiries are forgotten.
    s.reset()
    assert all(not q for q in s._given_up.values())


def test_unmatched_messages_expire_and_memory_is_bounded():
    clock = Clock()
    s = sync.StampSync(("depth", "embedding", "color"), tolerance_ns=MS, horizon_s=1.0,
                       capacity=4, clock=clock)
    for i in range(50):
        clock.t = i * 0.033
        s.add("depth", i * 33 * MS, i)
        s.add("embedding", i * 33 * MS, i)
    assert s.pending("depth") <= 4 and s.pending("embedding") <= 4
    assert s.drops["overflow"] == 2 * (50 - 4)
    assert s.starved() == ("color",)
    clock.t = 100.0                                          # everything waited too long
    s.add("color", 49 * 33 * MS, "c")
    assert s.drops["expired"] == 8 and s.pending() == 1


def test_a_stream_may_hold_more_than_the_others():
    """``capacities``: a pose topic at hundreds of Hz (128 bytes a message) holds more
    than the images beside it; raising ``capacity`` for a while raises it for all, and
    none falls below its own."""
    clock = Clock()
    s = sync.StampSync(("embedding", "color", "pose"), tolerance_ns=MS, horizon_s=10.0,
                       capacity=4, clock=clock, capacities={"pose": 12})
    for i in range(20):
        s.add("color", i * 10 * MS, i)
        s.add("pose", i * 10 * MS, i)
    assert (s.pending("color"), s.pending("pose")) == (4, 12)
    assert s.capacity_of("embedding") == 4 and s.capacity_of("pose") == 12
    s.capacity = 16
    assert s.capacity_of("pose") == s.capacity_of("color") == 16
    # The embedding of a frame whose pose is still held pairs; its colour was pushed out.
    assert s.add("embedding", 10 * 10 * MS, "e") == []
    assert s.drops_by_stream[("color", "overflow")] == 16
    with pytest.raises(ValueError, match="unknown streams"):
        sync.StampSync(("a", "b"), tolerance_ns=0, capacities={"c": 3})
    # A stream that never comes is named after starve_after losses, whatever the capacity.
    for starve_after, named in ((3, ("b",)), (0, ())):
        clock = Clock()
        s = sync.StampSync(("a", "b"), tolerance_ns=MS, horizon_s=1.0, capacity=100,
                           clock=clock, starve_after=starve_after)
        for i in range(3):
            s.add("a", i * 10 * MS, i)
        clock.t = 2.0
        s.add("a", 100 * MS, "x")                # the first three expire
        assert s.drops["expired"] == 3 and s.starved() == named


def test_a_message_is_tried_only_against_the_frames_within_its_tolerance(monkeypatch):
    """Each message tried every pending reference message against every queue: a 1 kHz
    pose topic whose stamps never matched, beside 20 embeddings waiting (their colour and
    depth there), took 65 % of a core in the pairing alone (measured here; 15 % now, the
    rest its queues' upkeep). A message can only
    complete the reference messages within the tolerance of it, so only they are tried."""
    calls = []
    real = sync.nearest
    monkeypatch.setattr(sync, "nearest", lambda times, t: calls.append(t) or real(times, t))
    s = sync.StampSync(("embedding", "color", "pose"), tolerance_ns=20 * MS, horizon_s=60.0,
                       capacity=4000, clock=Clock())
    for k in range(20):
        s.add("color", k * 100 * MS, k)
        s.add("embedding", k * 100 * MS, k)     # tried once each: no pose yet
    assert len(calls) == 2 * 20 and s.groups == 0
    calls.clear()
    for i in range(1000):                      # poses 45-55 ms off every frame: no pair
        s.add("pose", (i // 50) * 100 * MS + 45 * MS + (i % 50) * MS // 5, i)
    assert calls == [] and s.groups == 0
    # A pose near one of them pairs it, and supersedes the older ones.
    got = s.add("pose", 1005 * MS, "p")
    assert [g[0] for g in got] == [1000 * MS] and s.drops["superseded"] >= 10
    assert s.pending("embedding") == 9


def test_unknown_stream_is_a_clear_error():
    s = sync.StampSync(("depth",), tolerance_ns=MS)
    with pytest.raises(KeyError, match="unknown stream"):
        s.add("colour", 0, None)
    with pytest.raises(ValueError, match="distinct"):
        sync.StampSync(("a", "a"), tolerance_ns=0)


def test_nearest_and_pose_interpolation():
    times = np.array([100, 200], np.int64)
    assert sync.nearest(times, 160) == (1, 40)
    assert sync.nearest(np.array([], np.int64), 5)[0] == -1
