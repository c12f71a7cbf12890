"""Stamp pairing: the one place where messages of several streams are matched by stamp.

Offline (:class:`..data.bag.FrameReader`) and online (the engine's stages)
match with the same rule: the nearest stamp within a tolerance wins, and
poses may be interpolated between two samples at most ``max_gap_ns`` apart.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import numpy as np

from .camera import invert_pose, matrix_to_quat, pose_from_tq
from .msgconv import MessageError, pose_to_matrix, stamp_to_ns
from .params import param


def max_jump_param() -> Any:
    """The ``sync_max_jump_s`` parameter of a stage that pairs messages (:class:`StampSync`
    ``max_jump_ns``): one definition for the embedding, mapper and discovery stages."""
    return param(30.0, "a message stamped more than this ahead of the last frame paired, "
                 "beyond the time that has passed since (a live stream that paused is no "
                 "jump), is dropped as a bad stamp (a driver glitch), unless stamps keep "
                 "jumping (10 "
                 "messages in a row: a new bag, a camera restarted after a pause), when "
                 "pairing restarts on the new timeline (0 = no limit)", lo=0.0, hi=1e9,
                 unit="s")


def nearest(times: np.ndarray, t: int) -> tuple[int, int]:
    """Index of the entry of sorted int64 ``times`` nearest ``t``, and |difference| (ns)."""
    j = int(np.searchsorted(times, t))
    cands = [k for k in (j - 1, j) if 0 <= k < len(times)]
    if not cands:
        return -1, 1 << 62
    k = min(cands, key=lambda c: abs(int(times[c]) - t))
    return k, abs(int(times[k]) - t)


def interpolate_pose(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    """Pose a fraction ``w`` of the way from a to b (linear translation, slerp rotation)."""
    qa, qb = np.array(matrix_to_quat(a[:3, :3])), np.array(matrix_to_quat(b[:3, :3]))
    if qa @ qb < 0:
        qb = -qb
    cos = float(np.clip(qa @ qb, -1.0, 1.0))
    ang = math.acos(cos)
    if ang < 1e-9:
        q = qa
    else:
        q = (math.sin((1 - w) * ang) * qa + math.sin(w * ang) * qb) / math.sin(ang)
    return pose_from_tq((1 - w) * a[:3, 3] + w * b[:3, 3], q)


def pose_at(times: np.ndarray, poses: Sequence[Any], t: int, skew_ns: int,
            max_gap_ns: int = 0) -> np.ndarray:
    """Pose at stamp ``t`` from a sorted timeline of poses (entries may be error strings).

    Exact stamp first; then interpolation between the two samples around ``t``
    if they are at most ``max_gap_ns`` apart (0 = never); then the nearest
    sample within ``skew_ns``. Raises LookupError saying why none fits.
    """
    if len(times) == 0:
        raise LookupError("no pose samples")
    k, d = nearest(times, t)
    j = int(np.searchsorted(times, t))
    if d > 0 and max_gap_ns > 0 and 0 < j < len(times):
        t0, t1 = int(times[j - 1]), int(times[j])
        a, b = poses[j - 1], poses[j]
        if t1 - t0 <= max_gap_ns and isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
            return interpolate_pose(a, b, (t - t0) / (t1 - t0))
    if d > skew_ns:
        gap = f" and none to interpolate within {max_gap_ns / 1e6:g} ms" if max_gap_ns else ""
        raise LookupError(f"no sample within {skew_ns / 1e6:g} ms{gap}")
    if isinstance(poses[k], str):
        raise LookupError(f"invalid sample: {poses[k]}")
    return poses[k]


class StampSync:
    """Groups the messages of several streams by header stamp (no message_filters needed).

    ``add(stream, stamp_ns, value)`` stores a message and returns the groups it
    completed, oldest first, as ``(stamp_ns, {stream: value})``. A group is one
    message of every stream whose stamp is within ``tolerance_ns`` of a message of
    the first stream (the reference, e.g. the depth frame; its stamp is the
    group's), the nearest one winning. Nothing waits forever and memory stays
    bounded whatever arrives:

    - a message unmatched for ``horizon_s`` seconds of the clock expires, and
      messages older than a group's are superseded (they can never pair now);
    - a stream holds at most ``capacity`` messages, or its own number in ``capacities``
      if that is more (a pose topic at a motion capture's 360 Hz next to a 30 Hz camera's
      images: 128 bytes a pose against 2 MB a frame); the oldest goes first;
    - a second message with a stamp already pending in its stream is a duplicate;
    - a message older than the last group (minus the tolerance) can never be
      paired any more and is dropped as out of order, unless stamps keep going
      back (``reset_after`` such messages in a row, e.g. a bag replayed in a loop,
      or a clock reset): then the pairing restarts on the new timeline;
    - with ``max_jump_ns``, a message more than that ahead of the last group, beyond the
      time the clock says has passed since that group (a camera's stream that stopped for
      a minute and resumes is on time), is dropped as a jump, unless stamps keep jumping
      (``reset_after`` such messages in a row: a new bag, a camera restarted after a long
      pause): then the pairing restarts on the new timeline. One frame with a corrupt
      stamp (a driver's glitch, 10^6 s ahead) would otherwise become the timeline: every
      later good frame would be older than it and dropped until the reset, and the
      stages' stamp-based decisions (a keyframe every ``max_interval`` of stamp time)
      would wait for the stream to catch up with the bad stamp.

    Every drop is counted by reason in :attr:`drops`; duplicates, out-of-order
    stamps, jumps and time resets are also passed to ``on_anomaly(stream, reason,
    stamp_ns, detail)`` (the stages report them as problems), and so is a message of
    the reference stream that is given up unpaired (``unpaired``: it expired, or a newer
    one paired first) once the streams have paired before (``detail`` names the streams
    that had no message near its stamp: a frame whose pose never came is reported, not
    only counted; before the first group, partners sent before the node subscribed are
    expected to be missing and are not), or ``late`` when its partners did come but had
    been given up before it arrived, expired or pushed out of a full queue (``detail``:
    those streams and how long before it they came; the stage upstream is that far
    behind); before the first group, a message of the reference stream that expires while
    every stream it missed arrives is ``apart`` (``detail``: how far from its stamp the
    nearest message of each is: stamps that never agree, so nothing ever pairs) or
    ``late``;
    :meth:`starved` names streams that do not arrive while others do (a wrong topic
    name), which a node reports in a warning.
    """

    REASONS = ("expired", "superseded", "overflow", "duplicate", "out_of_order", "jump")

    def __init__(self, streams: Sequence[str], tolerance_ns: int, horizon_s: float = 2.0,
                 capacity: int = 64, reset_after: int = 10, clock=None,
                 on_anomaly=None, max_jump_ns: int = 0,
                 capacities: dict[str, int] | None = None, starve_after: int = 0) -> None:
        import collections
        import time

        if len(streams) < 1 or len(set(streams)) != len(streams):
            raise ValueError(f"streams must be distinct names, got {list(streams)}")
        self.streams = tuple(streams)
        self.tolerance_ns = int(tolerance_ns)
        self.horizon_s = float(horizon_s)
        self.capacity = int(capacity)
        unknown = set(capacities or ()) - set(self.streams)
        if unknown:
            raise ValueError(f"capacities for unknown streams {sorted(unknown)}")
        self.capacities = {s: int(n) for s, n in (capacities or {}).items()}
        self.starve_after = int(starve_after)
        self.reset_after = int(reset_after)
        self.max_jump_ns = int(max_jump_ns)
        self._clock = clock or time.monotonic
        # stream -> list of (stamp, arrival time, value), kept sorted by stamp
        self._pending: dict[str, list[tuple[int, float, Any]]] = {s: [] for s in streams}
        self.drops: collections.Counter = collections.Counter()
        self.drops_by_stream: collections.Counter = collections.Counter()
        self.groups = 0
        self.received = 0  # messages offered, of every stream (nothing yet: wrong topics?)
        self.resets = 0
        self.last_stamp: int | None = None
        self._last_group_at = 0.0  # clock time of the group that set last_stamp
        self._backwards = 0
        self._jumps = 0
        # Messages off the timeline (back, or ahead by a jump) held until it is clear
        # whether the stream restarted (reset_after of them in a row) or they were strays.
        self._held: list[tuple[str, int, Any, str, str]] = []
        self._since_group = collections.Counter()
        # Per partner stream, the (stamp, arrival) of its recent messages given up (expired,
        # or pushed out of a full queue): a reference message arriving after its partners
        # were given up is reported as late, not as one whose partners never came.
        self._given_up = {s: collections.deque(maxlen=max(1, self.capacity_of(s)))
                         for s in self.streams[1:]}
        self._on_anomaly = on_anomaly

    def _anomaly(self, stream: str, reason: str, stamp_ns: int, detail: str = "") -> None:
        if self._on_anomaly is not None:
            self._on_anomaly(stream, reason, stamp_ns, detail)

    def _drop(self, stream: str, reason: str, n: int = 1) -> None:
        if n:
            self.drops[reason] += n
            self.drops_by_stream[(stream, reason)] += n

    def capacity_of(self, stream: str) -> int:
        """The most messages ``stream`` holds: ``capacity``, or its own in ``capacities``
        if that is more (``capacity`` may be raised for a while, as the mapper does while
        its pose source is chosen)."""
        return max(self.capacity, self.capacities.get(stream, 0))

    def pending(self, stream: str | None = None) -> int:
        """Messages waiting for their partners (in one stream, or in all)."""
        if stream is not None:
            return len(self._pending[stream])
        return sum(len(q) for q in self._pending.values())

    def starved(self) -> tuple[str, ...]:
        """Streams with nothing received since the last group while the others have had at
        least ``starve_after`` messages (0: ``capacity``) expire or overflow meanwhile."""
        lost = sum(n for (s, r), n in self._since_group.items() if r in ("expired", "overflow"))
        if lost < (self.starve_after or self.capacity):
            return ()
        return tuple(s for s in self.streams if not self._since_group[(s, "received")])

    def reset(self) -> None:
        """Forget everything pending and the timeline (counters are kept)."""
        for q in self._pending.values():
            q.clear()
        self.last_stamp = None
        self._backwards = 0
        self._jumps = 0
        self._held = []
        self._since_group.clear()
        for q in self._given_up.values():
            q.clear()

    def _missing(self, stamp_ns: int) -> list[str]:
        """The streams with no pending message within the tolerance of ``stamp_ns``."""
        return [s for s in self.streams[1:]
                if not any(abs(e[0] - stamp_ns) <= self.tolerance_ns for e in self._pending[s])]

    def _nearest_offset(self, stream: str, stamp_ns: int) -> int | None:
        """Signed ns from ``stamp_ns`` to the nearest message ``stream`` has pending or gave
        up recently; None if it has none."""
        stamps = [e[0] for e in self._pending[stream]] + [st for st, _ in self._given_up[stream]]
        return min((t - stamp_ns for t in stamps), key=abs, default=None)

    def _report_unpaired(self, entries, expired: bool = False) -> None:
        """Report the reference stream's ``entries`` given up unpaired (expired, or older
        than a group just made), naming the streams that had nothing near each. Before the
        first group, partners sent before the node subscribed are expected to be missing:
        only an entry that ``expired`` while every stream it missed does arrive is reported,
        as ``apart`` with how far the nearest message of each is (stamps that never agree:
        a pose stamped on arrival, colour and depth stamped apart), or ``late``; until then
        a node whose inputs never paired said nothing at all."""
        if not self.groups and not expired:
            return
        for stamp, arrival, _ in entries:
            missing = self._missing(stamp)
            late = {}  # stream -> seconds its message came before this one (given up)
            for s in missing:
                near = [t for st, t in self._given_up[s] if abs(st - stamp) <= self.tolerance_ns]
                if near:
                    late[s] = arrival - max(near)
            absent = [s for s in missing if s not in late]
            if not self.groups:
                offsets = {s: self._nearest_offset(s, stamp) for s in absent}
                if any(d is None for d in offsets.values()):
                    continue  # a stream with nothing yet: starved() names it
                if offsets:
                    self._anomaly(self.streams[0], "apart", stamp, ", ".join(
                        f"the nearest {s} is stamped {abs(d) / 1e6:.1f} ms "
                        f"{'after' if d > 0 else 'before'} it" for s, d in offsets.items())
                        + f" (sync tolerance {self.tolerance_ns / 1e6:g} ms)")
                    continue
            if absent:
                self._anomaly(self.streams[0], "unpaired", stamp, ", ".join(absent))
            elif late:
                self._anomaly(self.streams[0], "late", stamp,
                              f"{', '.join(late)} ({max(late.values()):.1f} s before it)")

    def _expire(self, now: float) -> None:
        self._report_unpaired([e for e in self._pending[self.streams[0]]
                               if now - e[1] > self.horizon_s], expired=True)
        for s, q in self._pending.items():
            gone = [e for e in q if now - e[1] > self.horizon_s]
            if gone:
                if s in self._given_up:
                    self._given_up[s].extend((e[0], e[1]) for e in gone)
                self._drop(s, "expired", len(gone))
                self._since_group[(s, "expired")] += len(gone)
                q[:] = [e for e in q if now - e[1] <= self.horizon_s]

    def add(self, stream: str, stamp_ns: int, value: Any) -> list[tuple[int, dict[str, Any]]]:
        """Store one stream's message; the groups it completed, oldest first (class doc)."""
        if stream not in self._pending:
            raise KeyError(f"unknown stream {stream!r}; streams: {self.streams}")
        stamp_ns = int(stamp_ns)
        self.received += 1
        now = self._clock()
        self._expire(now)
        self._since_group[(stream, "received")] += 1
        if self.last_stamp is not None and stamp_ns < self.last_stamp - self.tolerance_ns:
            self._backwards += 1
            if self._backwards < self.reset_after:
                self._held.append((stream, stamp_ns, value, "out_of_order", ""))
                return []
            return self._restart(stream, stamp_ns, value, now)
        elif (self.last_stamp is not None and self.max_jump_ns > 0
              and stamp_ns > self.last_stamp + self.max_jump_ns
              + max(0, int((now - self._last_group_at) * 1e9))):
            self._jumps += 1
            if self._jumps < self.reset_after:
                self._held.append((stream, stamp_ns, value, "jump",
                                   f"{(stamp_ns - self.last_stamp) / 1e9:.3g} s"))
                return []
            return self._restart(stream, stamp_ns, value, now)
        else:
            self._backwards = 0
            self._jumps = 0
            self._drop_held()
        return self._store(stream, stamp_ns, value, now)

    def _restart(self, stream: str, stamp_ns: int, value: Any, now: float
                 ) -> list[tuple[int, dict[str, Any]]]:
        """Stamps kept going back (or jumping): the pairing restarts on the new timeline,
        with the messages held on the way there (a bag played again into running nodes
        lost its first frames of every stream, and the views they made, until a reset)."""
        held = self._held
        self._held = []
        self.resets += 1
        self._anomaly(stream, "time_reset", stamp_ns)
        self.reset()
        groups = []
        for h_stream, h_stamp, h_value, _, _ in held:
            groups += self._store(h_stream, h_stamp, h_value, now)
        return groups + self._store(stream, stamp_ns, value, now)

    def _drop_held(self) -> None:
        """The old timeline went on: the messages held against a restart were strays."""
        for stream, stamp_ns, _, reason, detail in self._held:
            self._drop(stream, reason)
            self._anomaly(stream, reason, stamp_ns, detail)
        self._held = []

    def _store(self, stream: str, stamp_ns: int, value: Any, now: float
               ) -> list[tuple[int, dict[str, Any]]]:
        """Queue one message on the current timeline; the groups it completed."""
        queue = self._pending[stream]
        if any(s == stamp_ns for s, _, _ in queue):
            self._drop(stream, "duplicate")
            self._anomaly(stream, "duplicate", stamp_ns)
            return []
        queue.append((stamp_ns, now, value))
        queue.sort(key=lambda e: e[0])
        if len(queue) > self.capacity_of(stream):
            if stream in self._given_up:
                self._given_up[stream].append((queue[0][0], queue[0][1]))
            del queue[0]
            self._drop(stream, "overflow")
            self._since_group[(stream, "overflow")] += 1
        return self._match(stream, stamp_ns)

    def _match(self, stream: str, stamp_ns: int) -> list[tuple[int, dict[str, Any]]]:
        """The groups a new message (``stream``, ``stamp_ns``) completed. Only the reference
        messages within the tolerance of it can have become complete (none was before it
        came, and dropping messages completes nothing), so only they are tried: with long
        queues (a pose topic at hundreds of Hz, a 90 Hz camera) every message tried every
        pending reference message against every queue, 65 % of a core for a 1 kHz pose
        stream whose stamps never matched."""
        out = []
        ref_name = self.streams[0]
        refs = self._pending[ref_name]
        times: dict[str, np.ndarray] = {}  # stamps of each queue, until a group changes them
        i = 0
        while i < len(refs):
            ref_stamp, _, ref_value = refs[i]
            if (ref_stamp != stamp_ns if stream == ref_name
                    else abs(ref_stamp - stamp_ns) > self.tolerance_ns):
                i += 1
                continue
            picked = {}
            for s in self.streams[1:]:
                q = self._pending[s]
                if s not in times:
                    times[s] = np.fromiter((e[0] for e in q), np.int64, len(q))
                j, d = nearest(times[s], ref_stamp)
                if j < 0 or d > self.tolerance_ns:
                    break
                picked[s] = j
            else:
                self._report_unpaired(refs[:i])
                group = {ref_name: ref_value}
                # The group and everything older in each stream can never pair again.
                for s, j in picked.items():
                    group[s] = self._pending[s][j][2]
                    self._drop(s, "superseded", j)
                    del self._pending[s][: j + 1]
                self._drop(ref_name, "superseded", i)
                del refs[: i + 1]
                self.last_stamp = ref_stamp
                self._last_group_at = self._clock()
                self.groups += 1
                self._since_group.clear()
                out.append((ref_stamp, group))
                times.clear()
                i = 0
                continue
            i += 1
        return out


def tf_chain(parent: dict[str, str], frame: str) -> list[str]:
    """``frame``, its parent, its parent's parent ... up to the root of its tree in a
    child -> parent map. In a loop (a malformed /tf) the walk stops before the first frame
    it would visit again, so no frame is listed twice."""
    out, seen = [frame], {frame}
    while out[-1] in parent and parent[out[-1]] not in seen:
        out.append(parent[out[-1]])
        seen.add(out[-1])
    return out


def tf_root(parent: dict[str, str], frame: str) -> str:
    """The root of ``frame``'s tree in a child -> parent map; in a loop, the smallest
    name of the loop (the same for every frame on or above it)."""
    chain = tf_chain(parent, frame)
    if chain[-1] not in parent:
        return chain[-1]
    return min(chain[chain.index(parent[chain[-1]]):])


class TfBuffer:
    """Transforms from /tf (time-stamped) and /tf_static, composed along the tree.

    Filled with tf2_msgs/TFMessage-like messages (duck-typed: rosbags messages
    offline, rclpy ones online) in any order; a lookup interpolates or takes the
    nearest sample of each edge (:func:`pose_at`). ``horizon_ns`` > 0 keeps only
    that much history per edge behind its newest sample (a live buffer stays
    bounded); 0 keeps everything (a bag read once).
    """

    def __init__(self, horizon_ns: int = 0) -> None:
        import collections

        self.horizon_ns = int(horizon_ns)
        self.parent: dict[str, str] = {}
        self.static: dict[str, np.ndarray] = {}                # child -> T_parent_child
        self.dynamic: dict[str, list[tuple[int, np.ndarray | str]]] = \
            collections.defaultdict(list)                      # child -> [(stamp, T or error)]
        self._times: dict[str, np.ndarray] = {}
        self._dirty: set[str] = set()

    def add(self, msg: Any, static: bool) -> None:
        for ts in msg.transforms:
            parent, child = ts.header.frame_id.lstrip("/"), ts.child_frame_id.lstrip("/")
            self.parent.setdefault(child, parent)
            try:
                T: np.ndarray | str = pose_to_matrix(ts)
            except MessageError as err:
                T = str(err)
            if static:
                if isinstance(T, np.ndarray):
                    self.static[child] = T
            else:
                self.dynamic[child].append((stamp_to_ns(ts.header.stamp), T))
                self._dirty.add(child)

    def _sorted(self, child: str) -> np.ndarray | None:
        if child in self._dirty:
            items = self.dynamic[child]
            items.sort(key=lambda x: x[0])
            if self.horizon_ns > 0 and items:
                newest = items[-1][0]
                items[:] = [e for e in items if e[0] >= newest - self.horizon_ns]
            self._times[child] = np.array([s for s, _ in items], dtype=np.int64)
            self._dirty.discard(child)
        return self._times.get(child)

    def frames(self) -> set[str]:
        return set(self.parent) | set(self.parent.values())

    def chain(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to its tree's root (:func:`tf_chain`)."""
        return tf_chain(self.parent, frame)

    def _edge(self, child: str, stamp: int, skew: int, max_gap: int) -> np.ndarray:
        if child in self.static:
            return self.static[child]
        times = self._sorted(child)
        if times is None or times.size == 0:
            raise LookupError(f"no transform for frame {child!r}")
        try:
            return pose_at(times, [T for _, T in self.dynamic[child]], stamp, skew, max_gap)
        except LookupError as err:
            raise LookupError(f"transform {self.parent[child]}->{child}: {err}") from None

    def lookup(self, parent: str, child: str, stamp: int, skew: int, max_gap: int = 0
               ) -> np.ndarray:
        """T_parent_child at ``stamp`` (per edge: exact, interpolated or nearest, see pose_at)."""
        up_c, up_p = self.chain(child), self.chain(parent)
        common = next((f for f in up_c if f in up_p), None)
        if common is None:
            raise LookupError(f"frames {parent!r} and {child!r} are not connected in /tf")

        def to_root(chain: list[str]) -> np.ndarray:
            T = np.eye(4)
            for f in chain[: chain.index(common)]:
                T = self._edge(f, stamp, skew, max_gap) @ T
            return T

        return invert_pose(to_root(up_p)) @ to_root(up_c)
