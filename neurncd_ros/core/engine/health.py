"""Health of a stage: counters, rates, problems by kind, state; what /diagnostics reports.

Every stage owns one :class:`Health`. Problems (a malformed message, a frame
skipped, a topic that never arrives) are counted by kind and logged at most
once per ``throttle_s`` per kind, each line saying how many of that kind came
since the last one, so one noisy kind never hides another. A failure (for
instance the field's training thread dying) puts the stage in the ``error``
state: it is logged and reported, and the stage stops publishing instead of
serving stale output. Nodes publish :meth:`snapshot` as a
diagnostic_msgs/DiagnosticStatus, as ROS 2 drivers do.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Callable

OK, WARN, ERROR = 0, 1, 2
"""Levels, as diagnostic_msgs/DiagnosticStatus numbers them."""

STATES = ("starting", "waiting", "running", "error", "stopped")

Logger = Callable[[int, str], None]
"""log(level, text): the node's logger (OK = info, WARN = warning, ERROR = error)."""


def _print_log(level: int, text: str) -> None:
    print(("info", "warning", "error")[level] + ": " + text, flush=True)


class Health:
    """Thread-safe counters, event rates, throttled problem reports and a state."""

    def __init__(self, name: str, log: Logger | None = None, throttle_s: float = 5.0,
                 window_s: float = 10.0, clock: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self._log = log or _print_log
        self.throttle_s = float(throttle_s)
        self.window_s = float(window_s)
        self._clock = clock
        self._lock = threading.Lock()
        self.counts: collections.Counter = collections.Counter()
        self.problems: collections.Counter = collections.Counter()
        self._events: dict[str, collections.deque] = {}
        self._last_report: dict[str, float] = {}
        self._unreported: collections.Counter = collections.Counter()
        self._last_problem_at = -1e18
        self.gauges: dict[str, object] = {}
        self.state = "starting"
        self.detail = ""
        self.error: str | None = None
        self._refused: dict[str, tuple[float, str]] = {}  # stream -> (when, reason)
        # stream -> stamps of its messages refused lately (those that had one)
        self._refused_stamps: dict[str, collections.deque] = {}

    # ------------------------------------------------------------ counting
    def count(self, key: str, n: int = 1) -> None:
        """Count n events of ``key`` (also timed, for :meth:`rate`)."""
        now = self._clock()
        with self._lock:
            self.counts[key] += n
            q = self._events.setdefault(key, collections.deque())
            q.append((now, n))
            while q and now - q[0][0] > self.window_s:
                q.popleft()

    def rate(self, key: str) -> float:
        """Events of ``key`` per second over the last ``window_s`` seconds."""
        now = self._clock()
        with self._lock:
            q = self._events.get(key)
            if not q:
                return 0.0
            while q and now - q[0][0] > self.window_s:
                q.popleft()
            if not q:
                return 0.0
            span = min(self.window_s, max(now - q[0][0], 1e-3))
            return sum(n for _, n in q) / span if len(q) > 1 else 0.0

    def gauge(self, key: str, value: object) -> None:
        """A current value reported as it is (queue length, iterations, ...)."""
        with self._lock:
            self.gauges[key] = value

    # ------------------------------------------------------------ problems
    def _due(self, key: str, now: float) -> int | None:
        """The throttle (caller holds the lock): None if ``key`` was logged less than
        throttle_s ago (this one is counted as unreported), else how many went unreported
        since its last line."""
        last = self._last_report.get(key)
        if last is not None and now - last < self.throttle_s:
            self._unreported[key] += 1
            return None
        self._last_report[key] = now
        return self._unreported.pop(key, 0)

    def problem(self, kind: str, message: str, level: int = WARN) -> None:
        """A problem of ``kind``: counted, logged at most once per throttle_s per kind."""
        now = self._clock()
        with self._lock:
            self.problems[kind] += 1
            self._last_problem_at = now
            more = self._due(kind, now)
        if more is None:
            return
        suffix = f" ({more} more of this kind since the last report)" if more else ""
        self._log(level, f"{message}{suffix}")

    def refuse(self, stream: str, kind: str, message: str, reason: str,
               stamp_ns: int | None = None) -> None:
        """A message of input ``stream`` arrived and was refused for ``reason`` (a colour
        image in an encoding the node cannot read, an embedding before its spec): a
        problem of ``kind`` logged as ``message``, and remembered for ``window_s`` so that
        :func:`report_starved` names the stream as refused, not as one that never comes.
        ``stamp_ns``: the refused message's stamp, so that a frame given up unpaired
        blames only a refusal of its own partner (:meth:`refused` ``near_ns``)."""
        with self._lock:
            self._refused[stream] = (self._clock(), reason)
            if stamp_ns is not None:
                self._refused_stamps.setdefault(stream, collections.deque(maxlen=64)).append(
                    int(stamp_ns))
        self.problem(kind, message)

    def refused(self, near_ns: int | None = None, within_ns: int = 0) -> dict[str, str]:
        """The input streams refused in the last ``window_s`` seconds, with the reason;
        with ``near_ns``, of the streams whose refused messages had stamps, only those
        with one within ``within_ns`` of it (a pose refused for its quaternion was blamed
        for a later frame given up for another reason)."""
        now = self._clock()
        with self._lock:
            out = {s: r for s, (t, r) in self._refused.items() if now - t <= self.window_s}
            if near_ns is not None:
                out = {s: r for s, r in out.items() if s not in self._refused_stamps
                       or any(abs(st - near_ns) <= within_ns
                              for st in self._refused_stamps[s])}
            return out

    def note(self, kind: str, message: str) -> None:
        """An event worth a log line that is not a problem (a decision the stage took, such
        as the pose source chosen): logged at info, throttled per kind like a problem,
        counted in :attr:`counts` as ``note.<kind>``; the diagnostics level stays OK."""
        now = self._clock()
        with self._lock:
            self.counts[f"note.{kind}"] += 1
            due = self._due(f"note.{kind}", now) is not None
        if due:
            self._log(OK, message)

    def fail(self, kind: str, message: str) -> None:
        """An error that stops the stage's output: state ``error``, logged, reported."""
        with self._lock:
            self.state, self.error = "error", f"{kind}: {message}"
        self.problem(kind, message, ERROR)

    def set_state(self, state: str, detail: str = "") -> None:
        if state not in STATES:
            raise ValueError(f"unknown state {state!r}; states: {STATES}")
        with self._lock:
            if self.state == "error" and state != "stopped":
                return  # an error is final until the stage is rebuilt
            self.state, self.detail = state, detail

    @property
    def failed(self) -> bool:
        return self.state == "error"

    # ------------------------------------------------------------ report
    def snapshot(self, rates: tuple[str, ...] = ()) -> dict:
        """{"level", "message", "values"}: values are strings, as DiagnosticStatus wants."""
        now = self._clock()
        values = {f"{k}_hz": f"{self.rate(k):.2f}" for k in rates}
        with self._lock:
            values.update({k: str(v) for k, v in sorted(self.counts.items())})
            values.update({f"problem.{k}": str(v) for k, v in sorted(self.problems.items())})
            values.update({k: str(v) for k, v in sorted(self.gauges.items())})
            values["state"] = self.state
            if self.state == "error":
                level, message = ERROR, self.error or "error"
            elif now - self._last_problem_at <= self.window_s:
                worst = max(self.problems, key=lambda k: self._last_report.get(k, -1e18))
                level, message = WARN, f"{self.state}; recent problem: {worst}"
            else:
                level = OK
                message = self.state + (f": {self.detail}" if self.detail else "")
        return {"level": level, "message": message, "values": values}


REFUSED_NEAR_NS = 100_000_000
"""A frame given up unpaired blames a refused message of its partner stream stamped this
near it (a refusal of another frame's partner is not why)."""


def sync_reporter(health, names: dict[str, str] | None = None):
    """An ``on_anomaly`` callback for :class:`..sync.StampSync` that reports to ``health``."""
    texts = {"duplicate": "a second message with stamp {s} on {n}: dropped",
             "out_of_order": "{n}: stamp {s} is older than a frame already paired: dropped",
             "jump": "{n}: stamp {s} is {d} ahead of the last frame paired (more than "
                     "sync_max_jump_s): dropped as a bad stamp; if stamps keep jumping "
                     "(a new bag, a restarted camera), pairing restarts",
             "unpaired": "{n}: the frame stamped {s} is given up unpaired: nothing came "
                         "on {d} within the sync tolerance: dropped",
             "late": "{n}: the frame stamped {s} came after its {d} had been given up "
                     "(they wait sync_horizon_s, and at most a queue's worth of them): "
                     "dropped; the stage upstream is that far behind (a slow machine, "
                     "large images): raise sync_horizon_s and queue_size, or lower the "
                     "load (smaller images, a lower rate)",
             "apart": "{n}: no frame has paired yet: the frame stamped {s} is given up: "
                      "{d}: the inputs' stamps must agree (a pose stamped when it was "
                      "computed rather than with its image's stamp, colour and depth not "
                      "registered to one stamp): stamp them alike, or raise "
                      "sync_tolerance_ms if they are this far apart by design",
             "time_reset": "{n}: stamps went back or jumped ahead (bag loop, new bag or "
                           "clock reset): pairing restarts"}

    def report(stream: str, reason: str, stamp_ns: int, detail: str = "") -> None:
        name = (names or {}).get(stream, stream)
        text = texts[reason].format(s=stamp_ns, n=name, d=detail)
        refused = health.refused(stamp_ns, REFUSED_NEAR_NS) if reason == "unpaired" else {}
        why = [f"{s} arrives but is refused: {r}" for s, r in refused.items()
               if s in detail.split(", ")]
        if why:
            # Its partner came and was refused before the pairing (Health.refuse): that,
            # not a lost message, is why nothing came on it.
            text = (f"{name}: the frame stamped {stamp_ns} is given up unpaired: "
                    + "; ".join(why) + ": dropped")
        elif reason == "unpaired" and any(k in detail for k in ("color", "depth")):
            # The usual cause of an image stream that keeps missing: a publisher with
            # default Fast DDS loses images over 1 MB before any subscriber sees them.
            text += ("; if this repeats, large images may be lost by their publisher: "
                     "start the camera driver with the shipped Fast DDS profile too "
                     "(README, 'Large images and Fast DDS')")
        health.problem(reason, text)
    return report


def no_camera_info(health) -> str:
    """Why a frame has no intrinsics: its camera info arrives but is refused (the reason
    :meth:`Health.refuse` recorded for stream ``camera_info``, e.g. a distortion), or none
    has come yet."""
    why = health.refused().get("camera_info")
    return (f"its camera info arrives but is refused: {why}" if why
            else "no camera info received yet")


def report_starved(health, starved: list[str], tolerance_ms: float, check: str,
                   topics: dict[str, str] | None = None) -> None:
    """Report the streams a :class:`..sync.StampSync` waits for while the others arrive
    (``StampSync.starved``), with what to ``check``; nothing if none. ``topics``: each
    stream's topic as the node resolved it (namespace, remaps), named beside the stream."""
    if not starved:
        return
    refused = health.refused()
    named = {s: f"{s} ({topics[s]})" if topics and s in topics else s for s in starved}
    absent = [named[s] for s in starved if s not in refused]
    parts = [f"waiting for {', '.join(absent)}: nothing arrives there while the other "
             f"{check} within {tolerance_ms:g} ms)"] if absent else []
    # A stream whose messages arrive and are refused never reaches the pairing, which
    # then sees nothing of it: name it as refused, with the reason.
    parts += [f"waiting for {s}: it arrives but is refused: {refused[s]}"  # names its topic
              for s in starved if s in refused]
    health.problem("starved", "; ".join(parts))
