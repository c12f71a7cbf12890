"""Poses for the mapper whatever the input carries: pose topic, /tf, or RGB-D odometry
(the pose stage), in one process and over DDS with the nodes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from neurncd_ros import config, synth
from neurncd_ros.core.camera import invert_pose, pose_distance
from neurncd_ros.core.data.bag import tf_msg
from neurncd_ros.core.engine.health import Health
from neurncd_ros.core.engine.poses import PoseStage

from fakeclock import MS, Clock  # noqa: E402,F401


@pytest.fixture(scope="module")
def walk():
    return list(synth.generate(1002, 30, synth.SynthConfig(width=160, height=120)))


def _stage(source: str, clock=None, tf_available: bool = True, log=None, odometry=None,
           **node) -> PoseStage:
    cfg = config.default()
    node = dataclasses.replace(cfg.mapper_node, pose_source=source, pose_auto_wait_s=1.0,
                               **node)
    return PoseStage(node, odometry or cfg.odometry, cfg.topics,
                     Health("mapper", log, node.log_throttle_s),
                     clock=clock or Clock(), tf_available=tf_available)


def _feed_images(st: PoseStage, frames, embedded=lambda i: True) -> list:
    """Colour and depth of each frame, then its embedding's stamp where the embedding
    node embedded it, as the mapper node hands them on."""
    out = []
    for i, f in enumerate(frames):
        out += st.offer_image("depth", f.stamp_ns, f.depth, f.intrinsics)
        out += st.offer_image("color", f.stamp_ns, f.rgb, f.intrinsics)
        if embedded(i):
            out += st.offer_embedding(f.stamp_ns)
    return out


def test_topic_poses_pass_through_and_nothing_is_published(walk):
    st = _stage("topic")
    f = walk[0]
    assert st.offer_pose(f.stamp_ns, f.pose) == [(f.stamp_ns, f.pose)]
    assert _feed_images(st, walk[:3]) == [] and not st.publishes


def test_auto_takes_the_pose_topic_when_one_publishes(walk):
    st = _stage("auto")
    assert _feed_images(st, walk[:2]) == []        # undecided: no pose yet
    assert st.offer_pose(walk[2].stamp_ns, walk[2].pose)
    assert st.mode == "topic" and not st.publishes


def test_auto_falls_back_to_odometry_that_follows_the_camera(walk):
    clock = Clock()
    st = _stage("auto", clock)
    early = _feed_images(st, walk[:5])
    assert early == [] and st.mode is None           # still waiting for a pose source
    clock.t = 2.0
    poses = dict(_feed_images(st, walk[5:]))
    assert st.mode == "odometry" and st.publishes
    # The frames tracked while the choice was open are handed on too.
    assert sorted(poses) == [f.stamp_ns for f in walk]
    # Relative motion matches the true one (the odometry's world is its first frame).
    first = walk[0].pose
    for f in walk[5::6]:
        if f.stamp_ns in poses:
            true_rel = invert_pose(first) @ f.pose
            dt, dr = pose_distance(true_rel, poses[f.stamp_ns])
            assert dt < 0.05 and dr < 3.0, (dt, dr)


def test_auto_chooses_odometry_on_the_clock_when_the_frames_stop(walk):
    """A stream shorter than pose_auto_wait_s (a 5-frame bag without poses): no frame comes
    after the wait, so the choice is made on the clock (the mapper polls it once a second)
    and the frames tracked meanwhile are handed on; until then they count as waiting (the
    mapper reports them pending, so bringup does not stop the nodes first). The choice
    was only made when a frame came after the wait: the mapper never chose, held the
    tracked poses and labelled nothing."""
    clock = Clock()
    st = _stage("auto", clock)
    assert st.poll() == [] and st.mode is None      # no frame yet: nothing to decide
    assert _feed_images(st, walk[:5]) == [] and st.waiting == 5
    assert st.poll() == [] and st.mode is None      # within the wait
    clock.t = 1.5
    poses = st.poll()
    assert st.mode == "odometry" and st.publishes
    assert [s for s, _ in poses] == [f.stamp_ns for f in walk[:5]]
    assert st.waiting == 0 and st.poll() == []
    # A pose topic chosen meanwhile: the odometry's poses are not handed on.
    st = _stage("auto", clock)
    _feed_images(st, walk[:3])
    assert st.offer_pose(walk[3].stamp_ns, walk[3].pose) and st.waiting == 0
    clock.t = 5.0
    assert st.poll() == [] and st.mode == "topic"


def _play_choosing(frames, node, lag_s: float = 0.2):
    """``frames`` at 30 Hz of a camera without poses through the mapper's pose and mapper
    stages as the node wires them (nodes/mapper.py: _image, _embedding, _offer_poses), on
    one clock: colour and depth of each frame as it comes, the embedding of every third
    ``lag_s`` later (embedding_node.max_rate_hz 10). The mapper stage, the pose stage, the
    stamps given a pose and those paired (colour, depth, embedding and pose)."""
    from neurncd_ros.core.engine.mapping import MapperStage
    from neurncd_ros.core.engine.offline import mapper_factory
    from neurncd_ros.core.engine.records import EmbeddingRecord, EmbeddingSpec

    cfg = config.load(None, {"mapper.fast.rays_per_iteration": 64})
    node = dataclasses.replace(cfg.mapper_node, pose_source="auto", **node)
    clock = Clock()
    health = Health("mapper", lambda level, text: None, node.log_throttle_s, clock=clock)
    st = MapperStage(node, mapper_factory(cfg), health, online=False, clock=clock)
    poses = PoseStage(node, cfg.odometry, cfg.topics, health, clock=clock)
    deciding = poses.mode is None
    st.set_pose_choice_open(deciding)
    st.offer_info(frames[0].intrinsics)
    spec = EmbeddingSpec(tuple(range(1, 10)))
    rng = np.random.default_rng(0)
    posed, paired = [], []

    def hand_on(out) -> None:
        nonlocal deciding
        if deciding:
            out = poses.poll() + out
        for stamp, T in out:
            posed.append(stamp)
            paired.extend(j.frame.stamp_ns for j in st.offer("pose", stamp, T))
        if deciding and poses.mode is not None and not poses.waiting:
            deciding = False
            st.set_pose_choice_open(False)

    events = []  # (arrival time, order, stream, frame)
    for i, f in enumerate(frames):
        t = i / 30
        events += [(t, 0, "depth", f), (t, 1, "color", f)]
        if i % 3 == 0:
            events.append((t + lag_s, 2, "embedding", f))
    for t, _, stream, f in sorted(events, key=lambda e: e[:2]):
        clock.t = t
        if stream == "embedding":
            rec = EmbeddingRecord(f.stamp_ns, rng.normal(size=f.depth.shape + (9,))
                                  .astype(np.float32), spec)
            paired.extend(j.frame.stamp_ns for j in st.offer("embedding", f.stamp_ns, rec))
            hand_on(poses.offer_embedding(f.stamp_ns, st.intrinsics))
        else:
            value = f.depth if stream == "depth" else f.rgb
            paired.extend(j.frame.stamp_ns for j in st.offer(stream, f.stamp_ns, value))
            hand_on(poses.offer_image(stream, f.stamp_ns, value, st.intrinsics))
    clock.t += 1.5  # the stream ended: the node's tick polls the choice once a second
    hand_on([])
    assert st.health.counts["frames_paired"] == len(paired)  # each admitted (no refusal)
    return st, poses, posed, paired


def test_auto_loses_no_frame_of_a_30_hz_camera_while_it_chooses(monkeypatch):
    """A 30 Hz bag without poses: while pose_source auto chooses (3 s), the frames'
    colour, depth and embeddings wait in the mapper's pairing for the poses the choice
    hands on. It held 60 messages per input (sync_horizon_s of a 30 Hz camera): the first
    31 colour and depth messages were pushed out before the choice, and the 11 embedded
    frames among them were lost without a word (problems {}; the exit line's unpaired
    inputs {"overflow": 62}); the pose stage kept the poses of the last 30 frames tracked
    meanwhile (odometry_frames all tracks 90). Every frame given a pose is paired now; a
    wait longer than the pairing holds is said."""
    frames = list(synth.generate(1005, 150, synth.SynthConfig(width=160, height=120)))
    embedded = [f.stamp_ns for f in frames[::3]]
    st, poses, posed, paired = _play_choosing(frames, {})
    assert poses.mode == "odometry" and st.sync.horizon_s == st.cfg.sync_horizon_s
    assert st.sync.drops["overflow"] == 0, dict(st.sync.drops)
    # Every frame the odometry gave a pose (all but one it lost, at 2 s) is paired, from
    # the first one on; 39 were (the 10 embedded in the first 31 frames lost, and one).
    assert len(posed) >= len(embedded) - 2 and posed[0] == embedded[0], posed
    assert paired == posed, sorted(set(posed) - set(paired))
    assert "pose_choice_overflow" not in st.health.problems
    # odometry_frames all: every frame is tracked while the choice is open (90 of them),
    # and the pose stage handed on the last 30: the first 20 embedded frames had no pose.
    st, poses, posed, paired = _play_choosing(frames, {"odometry_frames": "all"})
    assert len(posed) >= len(frames) - 2 and posed[0] == frames[0].stamp_ns
    assert paired == [s for s in posed if s in set(embedded)], paired[:3]
    assert st.sync.drops["overflow"] == 0
    # The pairing holds sync_horizon_s + pose_auto_wait_s of a camera of up to
    # MAX_CAMERA_HZ, the wait counted up to 10 s (CHOICE_HELD_S; 640x480 colour and depth,
    # 2.15 MB a frame): a longer wait loses the first frames, and says so. With none of it
    # counted, and sized for 30 Hz, the pairing holds its 60 as before: the first 31
    # frames are lost, said now.
    monkeypatch.setattr("neurncd_ros.core.engine.poses.CHOICE_HELD_S", 0.0)
    monkeypatch.setattr("neurncd_ros.core.engine.poses.MAX_CAMERA_HZ", 30.0)
    st, poses, posed, paired = _play_choosing(frames, {})
    assert st.sync.capacity == st.pairing_capacity == 60  # back to it once chosen
    assert poses.mode == "odometry" and st.health.problems["pose_choice_overflow"] > 0
    assert paired == [s for s in posed if s > frames[30].stamp_ns], paired[:3]


def _play_camera(hz: float, seconds: float = 6.0, pose_hz: float | None = None,
                 choose_at_s: float | None = None, burst_hz: float | None = None):
    """A camera of ``hz`` through the mapper stage's pairing on one clock, as the node hands
    its inputs on: colour and depth of each frame as it comes, and its pose (or a pose
    topic of ``pose_hz``, a motion capture's); the embedding of each frame the embedding
    node's rate gate at max_rate_hz 10 takes (every 2nd frame of 15 Hz, 3rd of 30, 6th of
    60, 9th of 90) 1.0-1.5 s after it, in stamp order. ``choose_at_s``: pose_source auto
    chooses odometry then, having tracked each embedded frame as its embedding came, and
    hands those poses on (then each one as its embedding comes). ``burst_hz``: colour,
    depth and pose at that rate instead, without embeddings (a driver gone wild). No
    field: the stamps embedded, the stamps paired, and the stage."""
    from neurncd_ros.core.camera import Intrinsics
    from neurncd_ros.core.engine.mapping import MapperStage
    from neurncd_ros.core.engine.records import EmbeddingRecord, EmbeddingSpec

    cfg = config.default()
    clock = Clock()
    health = Health("mapper", lambda level, text: None, 5.0, clock=clock)
    st = MapperStage(cfg.mapper_node, lambda *a: None, health, online=False, clock=clock)
    paired: list[int] = []
    st.admit = lambda frame, record: paired.append(frame.stamp_ns)
    st.offer_info(Intrinsics(8.0, 8.0, 4.0, 3.0, 8, 6))
    st.set_pose_choice_open(choose_at_s is not None)
    rgb, depth = np.zeros((6, 8, 3), np.uint8), np.ones((6, 8), np.float32)
    spec = EmbeddingSpec(tuple(range(1, 10)))
    rng = np.random.default_rng(7)
    events, embedded, arrival = [], [], 0.0  # (arrival time, order, stream, stamp)
    rate = burst_hz or hz
    for i in range(int(seconds * rate)):
        t, stamp = i / rate, 10**9 + round(i * 1e9 / rate)
        events += [(t, 0, "color", stamp), (t, 1, "depth", stamp)]
        if pose_hz is None and choose_at_s is None:
            events.append((t, 2, "pose", stamp))
        if burst_hz is None and (not embedded or stamp - embedded[-1] >= 0.09e9):
            embedded.append(stamp)
            arrival = max(arrival, t + rng.uniform(1.0, 1.5))  # the node embeds in turn
            events.append((arrival, 3, "embedding", stamp))
    for j in range(int(seconds * (pose_hz or 0))):
        events.append((j / pose_hz, 2, "pose", 10**9 + round(j * 1e9 / pose_hz)))
    tracked = []  # odometry's poses while auto chooses
    for t, _, stream, stamp in sorted(events, key=lambda e: e[:2]):
        clock.t = t
        if choose_at_s is not None and t >= choose_at_s and st.pose_choice_open:
            for s in tracked:
                st.offer("pose", s, np.eye(4))
            st.set_pose_choice_open(False)
        value = {"color": rgb, "depth": depth, "pose": np.eye(4),
                 "embedding": EmbeddingRecord(stamp, np.zeros((6, 8, 9), np.float32), spec)}
        st.offer(stream, stamp, value[stream])
        if stream == "embedding" and choose_at_s is not None:
            if st.pose_choice_open:
                tracked.append(stamp)
            else:
                st.offer("pose", stamp, np.eye(4))
    return embedded, paired, st


@pytest.mark.parametrize("choose_at_s", [None, 3.0], ids=["poses", "auto_choosing"])
@pytest.mark.parametrize("hz", [15, 30, 60, 90])
def test_the_mapper_pairs_every_embedded_frame_of_a_camera_of_up_to_90_hz(hz, choose_at_s):
    """A RealSense at 60 or 90 fps (some drivers at 15): the embedding of a frame comes
    1.0-1.5 s after it, and the pairing holds the colour and depth of every frame
    meanwhile. Sized for a 30 Hz camera (60 messages per input), it pushed them out first:
    of 60 embedded frames in 6 s, 60 Hz paired 10, 90 Hz 6 (overflow drops 900 and
    1440); while pose_source auto chose (3 s, 150 messages), 60 Hz paired 28, 90 Hz 19.
    15 and 30 Hz paired all, as they do now."""
    embedded, paired, st = _play_camera(hz, choose_at_s=choose_at_s)
    assert paired == embedded and len(embedded) >= 40
    assert st.sync.drops["overflow"] == 0, dict(st.sync.drops)
    assert "pose_choice_overflow" not in st.health.problems


@pytest.mark.parametrize("pose_hz", [120, 360])
def test_the_mapper_pairs_every_embedded_frame_with_a_motion_capture_pose_topic(pose_hz):
    """Poses from a motion capture (120-360 Hz) beside a 30 Hz camera: the pose input held
    as many messages as the images (60, half a second at 120 Hz), and the poses of frames
    whose embedding came a second later were pushed out: 120 Hz paired 5 of 60 embedded
    frames, 360 Hz 1. It holds sync_horizon_s of a 1 kHz pose topic now (under 1 MB)."""
    embedded, paired, st = _play_camera(30, pose_hz=pose_hz)
    assert paired == embedded and st.sync.drops["overflow"] == 0, dict(st.sync.drops)
    assert st.sync.capacity_of("pose") == 2000 and st.sync.capacity_of("color") == 180


def test_the_mapper_pairing_stays_bounded_under_a_1_khz_burst_of_stamps():
    """However fast the stamps come (a driver gone wild: 1 kHz of colour, depth and pose,
    no embedding), each input holds at most its capacity: 180 colour and depth images at
    the defaults (387 MB at 640x480), 2000 poses; 450 images while pose_source auto
    chooses (968 MB at 640x480)."""
    from neurncd_ros.core.engine import poses

    cfg = config.default().mapper_node
    assert poses.pairing_frames(cfg) == 180 and poses.choice_frames(cfg) == 450
    for choose_at_s, cap in ((None, 180), (10.0, 450)):
        _, paired, st = _play_camera(90, seconds=3.0, burst_hz=1000, choose_at_s=choose_at_s)
        assert paired == [] and st.sync.drops["overflow"] > 0
        held = {s: st.sync.pending(s) for s in st.STREAMS}
        assert held["color"] == held["depth"] == cap, held
        assert held["pose"] <= st.sync.capacity_of("pose") == 2000, held
        assert st.sync.capacity == cap


def test_auto_gives_the_first_seconds_of_a_90_hz_camera_their_tf_poses():
    """/tf links the frames 2.9 s into a 90 Hz stream (pose_source auto waits 3 s for it):
    every frame before it is looked up. The pose stage kept the stamps of the last 120
    (4 queue_size) and the first 141 frames went without a pose, while the mapper held
    their colour, depth and embedding for it; it keeps what the mapper holds now."""
    cfg = config.default()
    clock = Clock()
    st = PoseStage(cfg.mapper_node, cfg.odometry, cfg.topics, Health("mapper", None, 1.0),
                   clock=clock)
    depth = np.ones((2, 2), np.float32)
    stamps = [10**9 + round(i * 1e9 / 90) for i in range(int(2.9 * 90))]
    for i, stamp in enumerate(stamps):
        clock.t = i / 90
        assert st.offer_image("depth", stamp, depth, None) == []
    assert st.mode is None
    got = st.offer_tf(tf_msg(0, [("world", "camera", np.eye(4))]), static=True)
    assert st.mode == "tf" and [s for s, _ in got] == stamps


def test_odometry_tracks_only_the_frames_that_were_embedded(walk):
    """odometry_frames embedded: a third of the frames embedded, a third tracked (the
    mapper uses no other); all: every colour+depth pair, embeddings or not."""
    st = _stage("odometry")
    poses = dict(_feed_images(st, walk, embedded=lambda i: i % 3 == 0))
    assert sorted(poses) == [f.stamp_ns for f in walk[::3]]
    assert st.odometry.frames == len(walk[::3]) and st.publishes
    assert st.summary().startswith(f"pose source odometry: {len(walk[::3])} frames tracked")
    first = walk[0].pose
    for f in walk[::3]:
        dt, dr = pose_distance(invert_pose(first) @ f.pose, poses[f.stamp_ns])
        assert dt < 0.03 and dr < 2.0, (dt, dr)
    # A busy mapper may take an embedding before its frame's images: tracked when they come.
    st = _stage("odometry")
    late = []
    for f in walk[:6]:
        late += st.offer_embedding(f.stamp_ns)
        late += st.offer_image("depth", f.stamp_ns, f.depth, f.intrinsics)
        late += st.offer_image("color", f.stamp_ns, f.rgb, f.intrinsics)
    assert [s for s, _ in late] == [f.stamp_ns for f in walk[:6]]
    # Images before the first camera info: tracked with the intrinsics known by then.
    st = _stage("odometry")
    f = walk[0]
    st.offer_image("depth", f.stamp_ns, f.depth, None)
    st.offer_image("color", f.stamp_ns, f.rgb, None)
    assert [s for s, _ in st.offer_embedding(f.stamp_ns, f.intrinsics)] == [f.stamp_ns]
    st = _stage("odometry", odometry_frames="all")
    assert len(_feed_images(st, walk, embedded=lambda i: False)) == len(walk)
    assert st.odometry.frames == len(walk)
    # Embeddings 0.3 s apart (a busy embedding node): frames between them are tracked
    # too, one per odometry_gap_s (0.1 s, every third frame), so steps stay short.
    st = _stage("odometry")
    poses = dict(_feed_images(st, walk, embedded=lambda i: i % 9 == 0))
    assert {f.stamp_ns for f in walk[::9]} <= set(poses)
    assert sorted(poses) == [f.stamp_ns for f in walk[:28:3]]
    st = _stage("odometry", odometry_gap_s=0.0)
    poses = dict(_feed_images(st, walk, embedded=lambda i: i % 9 == 0))
    assert sorted(poses) == [f.stamp_ns for f in walk[::9]]


def test_odometry_losses_are_warnings_and_such_frames_get_no_pose(walk):
    """A covered lens for 4 frames: each is reported as lost (a warning naming the frame)
    and gets no pose; with new_segment_after 2 the first frame with depth after it
    starts a new segment, a warning too."""
    logs = []
    cfg = dataclasses.replace(config.default().odometry, new_segment_after=2)
    st = _stage("odometry", log=lambda level, text: logs.append((level, text)), odometry=cfg,
                log_throttle_s=0.0)
    covered = [dataclasses.replace(f, rgb=np.zeros_like(f.rgb), depth=np.zeros_like(f.depth))
               for f in walk[10:14]]
    other = list(synth.generate(2001, 3, synth.SynthConfig(width=160, height=120)))
    moved = [dataclasses.replace(o, stamp_ns=walk[-1].stamp_ns + (k + 1) * 33_000_000)
             for k, o in enumerate(other)]
    poses = dict(_feed_images(st, walk[:10] + covered + moved))
    assert not set(poses) & {f.stamp_ns for f in covered}
    assert {f.stamp_ns for f in walk[:10] + moved} <= set(poses)
    lost = [t for lvl, t in logs if "odometry lost" in t]
    assert len(lost) == 4 and all(lvl == 1 for lvl, t in logs if "odometry lost" in t)
    assert str(covered[0].stamp_ns) in lost[0]
    segment = [(lvl, t) for lvl, t in logs if "odometry new_segment" in t]
    assert len(segment) == 1 and segment[0][0] == 1 and st.odometry.segment == 1
    assert st.health.counts["odometry_lost"] == 4


def test_a_new_room_after_a_reset_starts_the_odometry_again(walk):
    """The mapper's ~/reset for a new room: the odometry forgets the old room's keyframes,
    so the new room's first frame is its origin and none of its frames is lost (they were
    tracked against the old room: lost, the first 10 frames, until a new segment)."""
    logs = []
    st = _stage("odometry", log=lambda level, text: logs.append((level, text)))
    assert len(_feed_images(st, walk[:10])) == 10
    other = list(synth.generate(2001, 12, synth.SynthConfig(width=160, height=120)))
    room = [dataclasses.replace(o, stamp_ns=walk[-1].stamp_ns + (k + 1) * 33_000_000)
            for k, o in enumerate(other)]
    st.reset_odometry()
    poses = dict(_feed_images(st, room))
    assert sorted(poses) == [f.stamp_ns for f in room], logs
    np.testing.assert_allclose(poses[room[0].stamp_ns], np.eye(4), atol=1e-9)
    first = room[0].pose
    dt, dr = pose_distance(invert_pose(first) @ room[-1].pose, poses[room[-1].stamp_ns])
    assert dt < 0.03 and dr < 2.0, (dt, dr)
    assert st.odometry.segment == 0 and "odometry_lost" not in st.health.counts
    assert st.odometry.frames == 22  # the exit line's counts go on
    assert st.summary().startswith("pose source odometry: 22 frames tracked")


def test_tf_poses_are_looked_up_at_each_frame_and_interpolated(walk):
    st = _stage("tf")
    cam = {f.stamp_ns: f.pose for f in walk}
    # /tf at 15 Hz, frames at 30 Hz: every other frame needs interpolation.
    base = np.eye(4)
    base[:3, 3] = [1.0, 2.0, 0.0]
    st.offer_tf(tf_msg(0, [("world", "base", base)]), static=True)
    got = []
    for i, f in enumerate(walk):
        got += st.offer_image("depth", f.stamp_ns, f.depth, f.intrinsics)
        if i % 2 == 0:
            got += st.offer_tf(tf_msg(f.stamp_ns, [("base", "camera",
                                                    invert_pose(base) @ f.pose)]), False)
    got = dict(got)
    assert len(got) >= len(walk) - 2 and st.publishes
    for stamp, T in got.items():
        dt, dr = pose_distance(T, cam[stamp])
        assert dt < 0.01 and dr < 0.5, (stamp, dt, dr)


def test_a_slow_tf_edge_is_interpolated_as_tf2_does(walk):
    """A robot's tree: map->odom from a localisation at 2 Hz, odom->camera at 30 Hz.
    Every frame between two map->odom samples gets its pose (at the old 100 ms limit,
    1 of 300 frames of such a stream got one)."""
    cam = {f.stamp_ns: f.pose for f in walk}
    drift = np.eye(4)
    drift[:3, 3] = [0.5, -0.2, 0.0]

    def poses(**node) -> dict:
        cfg = config.default()
        topics = dataclasses.replace(cfg.topics, world_frame="map", camera_frame="camera")
        st = PoseStage(dataclasses.replace(cfg.mapper_node, pose_source="tf", **node),
                       cfg.odometry, topics, Health("mapper", None, 1.0), clock=Clock())
        got = []
        for i, f in enumerate(walk):
            if i % 15 == 0:  # 2 Hz
                got += st.offer_tf(tf_msg(f.stamp_ns, [("map", "odom", drift)]), False)
            got += st.offer_tf(tf_msg(f.stamp_ns, [("odom", "camera",
                                                    invert_pose(drift) @ f.pose)]), False)
            got += st.offer_image("depth", f.stamp_ns, f.depth, f.intrinsics)
        return dict(got)

    got = poses()
    # Frames 0-15 lie between two map->odom samples; the later ones wait for the next.
    assert len(got) == 16 and set(got) <= set(cam)
    for stamp, T in got.items():
        dt, dr = pose_distance(T, cam[stamp])
        assert dt < 1e-6 and dr < 1e-4, (stamp, dt, dr)
    assert len(poses(tf_max_gap_ms=100.0)) == 2  # only the frames at a map->odom sample


def test_auto_gives_the_frames_before_the_first_tf_their_poses(walk):
    """With pose_source auto, frames whose depth came before /tf linked the frames are
    looked up once it does (they went without a pose: 10 of 300 with /tf 300 ms late)."""
    st = _stage("auto")
    cam = {f.stamp_ns: f.pose for f in walk}
    got = []
    for f in walk[:6]:  # /tf still silent
        got += st.offer_image("depth", f.stamp_ns, f.depth, f.intrinsics)
    assert st.mode is None and got == []
    for i, f in enumerate(walk):
        got += st.offer_tf(tf_msg(f.stamp_ns, [("world", "camera", f.pose)]), False)
        if i >= 6:
            got += st.offer_image("depth", f.stamp_ns, f.depth, f.intrinsics)
    got = dict(got)
    assert st.mode == "tf" and set(got) == set(cam)
    for stamp, T in got.items():
        assert pose_distance(T, cam[stamp])[0] < 1e-6


def test_tf_without_tf2_msgs_is_a_clear_error_and_auto_skips_it():
    with pytest.raises(ValueError, match="tf2_msgs"):
        _stage("tf", tf_available=False)
    st = _stage("auto", tf_available=False)
    st.offer_tf(tf_msg(0, [("world", "camera", np.eye(4))]), static=True)
    assert st.mode is None


@pytest.mark.parametrize("tf_available, why", [
    (False, "/tf cannot be read here (no tf2_msgs"),
    (True, "no /tf link from world to camera"),
])
def test_auto_says_why_it_chose_odometry(walk, tf_available, why):
    """A user whose poses are on /tf learns why the mapper tracks the camera itself."""
    clock, lines = Clock(), []
    st = _stage("auto", clock, tf_available=tf_available,
                log=lambda level, text: lines.append(text))
    _feed_images(st, walk[:3])
    clock.t = 2.0
    _feed_images(st, walk[3:6])
    assert st.mode == "odometry"
    note = [t for t in lines if t.startswith("pose source: odometry")]
    assert note and "no pose on /camera/pose within 1 s" in note[0] and why in note[0], lines


@pytest.mark.ros
def test_nodes_label_a_stream_without_poses_using_odometry(tmp_path):
    """A camera with no pose topic and no /tf: the mapper chooses odometry (auto), publishes
    the poses on /camera/pose for the others, and labels come out."""
    import time

    import rosutil
    from rosutil import apply_ros_env, camera_publishers, node_graph, publish_frame, spin_until

    domain = rosutil.domain(12)
    apply_ros_env(domain)
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Image

    from neurncd_ros.nodes.common import output_qos

    frames = list(synth.generate(1005, 90, synth.SynthConfig(width=160, height=120,
                                                             fps=10.0)))
    args = ["--ros-args", "-p", "mapper_node.pose_auto_wait_s:=1.0"]
    labels, poses = [], []
    with node_graph(domain, ("embedding", "mapper", "discovery"), args, tmp_path,
                    "camera_without_poses") as (node, procs):
        node.create_subscription(Image, "/neurncd/labels", labels.append, output_qos(50))
        node.create_subscription(PoseStamped, "/camera/pose", poses.append, output_qos(50))
        pubs = camera_publishers(node)
        assert spin_until(node, lambda: all(p.get_subscription_count() >= 2
                                            for p in list(pubs.values())[:2]), 120)
        end = time.monotonic() + 240
        i = 0
        while time.monotonic() < end and not (len(labels) >= 3 and len(poses) >= 10):
            f = frames[i % len(frames)]
            publish_frame(pubs, f, f.stamp_ns + (i // len(frames)) * 20_000_000_000)
            i += 1
            spin_until(node, lambda: False, 0.1)
        logs = {n: (tmp_path / f"{n}.log").read_text() for n in procs}
        assert len(poses) >= 10 and len(labels) >= 3, logs["mapper"][-3000:]
        assert "pose source: odometry" in logs["mapper"]
        assert all(p.poll() is None for p in procs.values())


@pytest.mark.ros
def test_nodes_label_a_short_stream_without_poses(tmp_path):
    """Five frames without poses, then nothing (a user's 5-frame bag replayed with bringup):
    the stream ends before pose_auto_wait_s (3 s), so the mapper chooses odometry on its
    clock, the frames' inputs wait for that choice, and all five are labelled. The mapper
    chose only when a frame came after the wait: it stayed undecided, labelled nothing and
    reported nothing pending, so bringup stopped the nodes as if done."""
    import rosutil
    from rosutil import apply_ros_env, camera_publishers, node_graph, publish_frame, spin_until

    domain = rosutil.domain(12)
    apply_ros_env(domain)
    from sensor_msgs.msg import Image

    from neurncd_ros.nodes.common import output_qos

    frames = list(synth.generate(1005, 5, synth.SynthConfig(width=160, height=120,
                                                            fps=10.0)))
    args = ["--ros-args", "-p", "embedding_node.max_rate_hz:=0.0"]
    labels = []
    with node_graph(domain, ("embedding", "mapper", "discovery"), args, tmp_path,
                    "short_camera_without_poses") as (node, procs):
        node.create_subscription(Image, "/neurncd/labels", labels.append, output_qos(50))
        pubs = camera_publishers(node)
        # Every node up and seeing its upstream node, as bringup waits before a bag.
        diag = rosutil.diagnostics_of(node, ("embedding", "mapper", "discovery"))
        assert spin_until(node, lambda: all(p.get_subscription_count() >= 2
                                            for p in list(pubs.values())[:2])
                          and len(diag) == 3 and all(
                              diag[n].get("upstream_publishers") == "1"
                              for n in ("mapper", "discovery")), 120)
        for f in frames:
            publish_frame(pubs, f)
            spin_until(node, lambda: False, 0.1)   # the camera's pace, 10 Hz
        spin_until(node, lambda: len(labels) >= 1, 60)
        logs = {n: (tmp_path / f"{n}.log").read_text() for n in procs}
        assert labels, (diag, logs)
        assert "pose source: odometry" in logs["mapper"]
        assert {lab.header.stamp.sec * 10**9 + lab.header.stamp.nanosec for lab in labels} \
            <= {f.stamp_ns for f in frames}


@pytest.mark.ros
def test_the_reset_services_start_a_new_room(tmp_path):
    """/mapper/reset and /discovery/reset over DDS, as the README has a user call them
    before a new room: the mapper's odometry starts again at the new room's first frame
    (it lost that room's first 10 frames against the old room's keyframes), and both
    say what they forgot."""
    import rosutil
    from rosutil import apply_ros_env, camera_publishers, node_graph, publish_frame, spin_until

    domain = rosutil.domain(12)
    apply_ros_env(domain)
    from geometry_msgs.msg import PoseStamped
    from std_msgs.msg import String
    from std_srvs.srv import Trigger

    from neurncd_ros.core.msgconv import class_table_from_text, pose_to_matrix
    from neurncd_ros.nodes.common import latched_qos, output_qos

    size = synth.SynthConfig(width=160, height=120, fps=10.0)
    old_room = list(synth.generate(1002, 6, size))
    new_room = [dataclasses.replace(f, stamp_ns=f.stamp_ns + 5_000_000_000)
                for f in synth.generate(2001, 6, size)]
    args = ["--ros-args", "-p", "mapper_node.pose_source:=odometry",
            "-p", "mapper_node.odometry_frames:=all"]
    poses = {}
    with node_graph(domain, ("mapper", "discovery"), args, tmp_path,
                    "new_room_camera") as (node, procs):
        node.create_subscription(PoseStamped, "/camera/pose", lambda m: poses.setdefault(
            m.header.stamp.sec * 10**9 + m.header.stamp.nanosec, pose_to_matrix(m)),
            output_qos(50))
        pubs = camera_publishers(node)
        assert spin_until(node, lambda: all(p.get_subscription_count() >= 1
                                            for p in pubs.values()), 120)

        def play(frames) -> None:
            for f in frames:  # each frame until its pose comes (best effort may lose one)
                for _ in range(20):
                    publish_frame(pubs, f)
                    if spin_until(node, lambda: f.stamp_ns in poses, 3.0):
                        break

        def call(service: str) -> str:
            client = node.create_client(Trigger, service)
            assert client.wait_for_service(timeout_sec=60), service
            future = client.call_async(Trigger.Request())
            assert spin_until(node, future.done, 60), service
            assert future.result().success
            return future.result().message

        play(old_room)
        assert {f.stamp_ns for f in old_room} <= set(poses)
        assert "odometry starts again" in call("/mapper/reset")
        assert "novel ids start from 100 again" in call("/discovery/reset")
        # The latched class table is emptied (it named the old room's ids to late
        # subscribers until the next label); a subscriber after the reset gets that.
        tables = []
        node.create_subscription(String, "/neurncd/classes", lambda m: tables.append(
            class_table_from_text(m.data)[2]), latched_qos())
        assert spin_until(node, lambda: tables, 30) and tables[-1] == {}
        play(new_room)
        mapper_log = (tmp_path / "mapper.log").read_text()
        assert {f.stamp_ns for f in new_room} <= set(poses), mapper_log[-3000:]
        np.testing.assert_allclose(poses[new_room[0].stamp_ns], np.eye(4), atol=1e-6)
        assert "odometry lost" not in mapper_log, mapper_log[-3000:]
        assert all(p.poll() is None for p in procs.values())
