"""Node processes from their first instant to their exit: a stop signal while a node is
still importing torch, bad parameter files and ROS arguments, a child of bringup killed
by a signal, a replay stopped mid-bag, and no callback left running when a node goes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import rosutil
from neurncd_ros.core.params import ConfigError
from rosutil import REPO, apply_ros_env, node_processes, ros_env, spin_until

pytestmark = pytest.mark.ros

BAD_YAML = "/**:\n  ros__parameters:\n    mapper:\n      backend: fast\n     iterations: 3\n"
BAD_SECTION = "/**:\n  ros__parameters:\n    mapper: 3\n"


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory):
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    path = tmp_path_factory.mktemp("bag") / "scene.mcap"
    write_bag(path, synth.generate(1003, 15, synth.SynthConfig(width=96, height=72)))
    return path


def _status_mask(pid: int, field: str) -> int:
    """A signal mask of /proc/<pid>/status (SigCgt: caught, SigBlk: blocked); 0 if gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1], 16)
    except OSError:
        pass
    return 0


def _catches(pid: int, *sigs: signal.Signals) -> bool:
    mask = _status_mask(pid, "SigCgt")
    return all(mask >> (s - 1) & 1 for s in sigs)


def _torch_loaded(pid: int) -> bool:
    try:
        return "libtorch" in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


def _wait_for(predicate, timeout: float) -> bool:
    """Poll a condition of another process (there is no event to block on) until true."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def _start(args: list[str], env: dict[str, str], ignore_sigint: bool = False,
           block: bool = False) -> subprocess.Popen:
    """``python args`` with stdout and stderr captured; ``ignore_sigint`` as `cmd &` from a
    script starts it; ``block``: SIGINT and SIGTERM blocked, as bringup starts a node."""
    def setup() -> None:
        if ignore_sigint:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        if block:
            signal.pthread_sigmask(signal.SIG_BLOCK, (signal.SIGINT, signal.SIGTERM))
    return subprocess.Popen([sys.executable, *args], env=env, cwd=REPO, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=setup)


def _finish(proc: subprocess.Popen, timeout: float) -> tuple[int | None, str]:
    """(exit code, output) once it exits within ``timeout``; (None, output) if it had to be
    killed."""
    try:
        out, err = proc.communicate(timeout=timeout)
        return proc.returncode, out + err
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        return None, out + err


@pytest.mark.parametrize("node_name, sig, ignore_sigint", [
    ("embedding", signal.SIGINT, True),   # `embedding &` from a script, stopped by kill -INT
    ("mapper", signal.SIGINT, False),     # Ctrl-C in a terminal
    ("discovery", signal.SIGTERM, True),
    ("replay", signal.SIGINT, True),
])
def test_signal_while_importing_exits_at_once_without_traceback(node_name, sig, ignore_sigint,
                                                                small_bag):
    """The handlers are in before torch loads, so a stop sent while the node imports is
    neither lost (SIGINT ignored) nor a KeyboardInterrupt traceback: exit 0 at once."""
    proc = _start(["-m", f"neurncd_ros.nodes.{node_name}", "--ros-args", "-p",
                   f"replay.bag:={small_bag}"], ros_env(rosutil.domain(14)), ignore_sigint)
    try:
        assert _wait_for(lambda: _catches(proc.pid, signal.SIGINT, signal.SIGTERM)
                         or proc.poll() is not None, 30)
        if node_name != "replay":
            assert not _torch_loaded(proc.pid), "the handlers came only after torch loaded"
        proc.send_signal(sig)
    finally:
        code, text = _finish(proc, 10)
    assert code == 0, text[-2000:]
    assert f"{node_name}: {sig.name} while starting: exiting" in text, text[-2000:]
    assert "Traceback" not in text, text[-2000:]


def test_signal_held_while_starting_is_handled_once_the_node_can(small_bag):
    """As bringup starts a node (stop signals blocked until its handlers are in), a signal
    sent at once after start is handled, not left pending forever (nor a traceback)."""
    proc = _start(["-m", "neurncd_ros.nodes.discovery"], ros_env(rosutil.domain(14)),
                  ignore_sigint=True, block=True)
    try:
        proc.send_signal(signal.SIGINT)
    finally:
        code, text = _finish(proc, 20)
    assert code == 0, text[-2000:]
    assert "Traceback" not in text, text[-2000:]


def _bringup(bag: Path, domain: int) -> subprocess.Popen:
    return _start(["-m", "neurncd_ros.nodes.bringup", "--bag", str(bag), "--stop-timeout",
                   "20"], ros_env(domain), ignore_sigint=True)


def _children(domain: int, parent: int) -> dict[str, int]:
    """Node name -> pid of bringup's children on ``domain``."""
    out = {}
    for pid in node_processes(domain):
        if pid == parent:
            continue
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        name = next((a.decode().rsplit(".", 1)[1] for a in cmd
                     if a.startswith(b"neurncd_ros.nodes.")), "")
        out[name] = pid
    return out


def test_bringup_stopped_while_its_nodes_start_stops_them_without_tracebacks(small_bag):
    """bringup started in the background and stopped while its nodes are still importing:
    it exits 0, and so do they, without a KeyboardInterrupt traceback; none is left."""
    domain = rosutil.domain(15)
    proc = _bringup(small_bag, domain)
    try:
        assert _wait_for(lambda: len(_children(domain, proc.pid)) == 3
                         or proc.poll() is not None, 60)
        proc.send_signal(signal.SIGINT)
    finally:
        code, text = _finish(proc, 40)
    assert code == 0, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert "bringup: SIGINT: stopping the nodes" in text, text[-3000:]
    assert not node_processes(domain), "a node outlived bringup"


def test_bringup_reports_a_child_killed_by_a_signal_as_128_plus_the_signal(small_bag):
    domain = rosutil.domain(15)
    proc = _bringup(small_bag, domain)
    try:
        assert _wait_for(lambda: "mapper" in _children(domain, proc.pid)
                         or proc.poll() is not None, 60)
        os.kill(_children(domain, proc.pid)["mapper"], signal.SIGKILL)
    finally:
        code, text = _finish(proc, 40)
    assert code == 128 + signal.SIGKILL, text[-3000:]
    assert ("bringup: mapper was killed by SIGKILL (exit code 137): stopping the others; "
            "bringup exits 137") in text, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    assert not node_processes(domain), "a node outlived bringup"


def _one_line_error(r: subprocess.CompletedProcess, expect: str) -> None:
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and expect in lines[0], r.stderr


@pytest.mark.parametrize("text, expect", [
    (BAD_YAML, "not valid YAML: line 5, column 6: expected <block end>"),
    # rcl would take the last value silently; the node refuses as `neurncd` does
    ("/**:\n  ros__parameters:\n    replay:\n      rate: 2.0\n      rate: 3.0\n",
     "parameter 'replay.rate' (node '/**') is given twice (lines 4 and 5)"),
])
def test_node_reports_a_bad_parameter_file_on_one_line(text, expect, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.replay", "--ros-args",
                        "--params-file", str(bad)], env=ros_env(rosutil.domain(14)),
                       capture_output=True, text=True, timeout=60, cwd=REPO)
    _one_line_error(r, f"replay: configuration error: {bad}: {expect}")


@pytest.mark.parametrize("args, expect", [
    (["-p", "foo"], "replay: error: Couldn't parse parameter override rule: '-p foo'"),
    (["--no-such-flag"], "replay: error: unknown ROS arguments"),
])
def test_node_reports_ros_arguments_rcl_refuses_on_one_line(args, expect):
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.replay", "--ros-args", *args],
                       env=ros_env(rosutil.domain(14)), capture_output=True, text=True,
                       timeout=60, cwd=REPO)
    _one_line_error(r, expect)
    assert "/project/src" not in r.stderr  # rcl's source locations are left out


@pytest.mark.parametrize("text, expect", [
    (BAD_YAML, "not valid YAML: line 5, column 6"),
    (BAD_SECTION, "mapper: section must be a mapping of parameters, got 3"),
])
def test_bringup_reports_a_bad_parameter_file_on_one_line(text, expect, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.bringup", "--params-file",
                        str(bad)], env=ros_env(rosutil.domain(15)), capture_output=True,
                       text=True, timeout=60, cwd=REPO)
    _one_line_error(r, f"bringup: configuration error: {bad}: {expect}")
    assert not node_processes(rosutil.domain(15))


@pytest.mark.parametrize("ros_args, expect", [
    (["-p", "discovery.mcl_inflation:=abc"], "discovery.mcl_inflation"),
    (["-p", "mapper.no_such_key:=1"], "mapper.no_such_key"),
    (["--params-file", "EXTRA"], "keyframes.min_rotation"),
    # refused by the embedding node alone, once the others had started
    (["-p", "backbone.kind:=esanet"], "kind=esanet needs checkpoint"),
])
def test_bringup_refuses_a_bad_value_once_before_starting_nodes(ros_args, expect, tmp_path):
    """A bad `-p` value (or one in a further --params-file) was refused by each node on its
    own: three identical errors and a supervisor that had started them all. Bringup checks
    the configuration its nodes would read and refuses it once, naming where it was given."""
    extra = tmp_path / "extra.yaml"
    extra.write_text("/**:\n  ros__parameters:\n    keyframes:\n      min_rotation: -5.0\n")
    ros_args = [str(extra) if a == "EXTRA" else a for a in ros_args]
    domain = rosutil.domain(15)
    r = subprocess.run([sys.executable, "-m", "neurncd_ros.nodes.bringup", "--ros-args",
                        *ros_args], env=ros_env(domain), capture_output=True, text=True,
                       timeout=60, cwd=REPO)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1 and lines[0].startswith("bringup: configuration error: "), r.stderr
    assert expect in lines[0], lines[0]
    origin = "given in params file" if "--params-file" in ros_args else "given with -p"
    assert origin in lines[0] or "unknown" in lines[0] or "backbone" in lines[0], lines[0]
    assert not node_processes(domain)


def test_bringup_checks_what_each_of_its_nodes_is_given(tmp_path):
    """A parameter file shared with other nodes (a camera driver's entry) or holding one
    entry per robot: bringup refused it for keys none of its nodes is given. It now checks
    each node's own view (/** and the entries naming it, in its namespace)."""
    from neurncd_ros.nodes.parameters import started_configuration

    shared = tmp_path / "shared.yaml"
    shared.write_text("/**:\n  ros__parameters:\n    mapper:\n      lambda_embedding: 0.5\n"
                      "camera_driver:\n  ros__parameters:\n    fps: 30\n"
                      "/robot2/*:\n  ros__parameters:\n    embedding_node:\n"
                      "      max_rate_hz: -3.0\n")
    nodes = ("embedding", "mapper", "discovery")
    cfg = started_configuration(shared, ["-r", "__ns:=/robot1"], nodes)
    assert cfg.mapper.lambda_embedding == 0.5
    with pytest.raises(ConfigError, match=r"max_rate_hz: -3.0 is out of range.*"
                                          r"\(node /robot2/embedding\)"):
        started_configuration(shared, ["-r", "__ns:=/robot2"], nodes)
    with pytest.raises(ConfigError, match="fps: unknown section"):
        started_configuration(shared, [])  # no nodes named: every entry, as before


def test_replay_stopped_mid_bag_says_so_and_where(small_bag):
    """A replay stopped by a signal does not claim to have finished: it tells how many of
    the bag's messages it published."""
    from neurncd_ros.core.data.bag import bag_topics

    domain = rosutil.domain(14)
    apply_ros_env(domain)
    import rclpy
    from sensor_msgs.msg import Image

    from neurncd_ros.nodes.common import sensor_qos

    total = sum(count for _, count in bag_topics(small_bag).values())
    rclpy.init()
    node = rclpy.create_node("replay_watcher")
    seen: list = []
    node.create_subscription(Image, "/camera/depth/image_raw", seen.append, sensor_qos(5))
    # It plays at once (it would wait 30 s for subscribers on the inputs not watched here).
    proc = _start(["-m", "neurncd_ros.nodes.replay", "--ros-args", "-p",
                   f"replay.bag:={small_bag}", "-p", "replay.rate:=0.05", "-p",
                   "replay.wait_for_subscribers_s:=0.0"], ros_env(domain))
    try:
        assert spin_until(node, lambda: bool(seen) or proc.poll() is not None, 60)
        proc.send_signal(signal.SIGTERM)
    finally:
        code, text = _finish(proc, 30)
        node.destroy_node()
        rclpy.shutdown()
    assert code == 0, text[-2000:]
    assert "replay finished" not in text, text[-2000:]
    assert f"of the bag's {total} messages" in text and "replay stopped after " in text, \
        text[-2000:]


def test_replay_says_it_waits_for_subscribers_and_that_it_stopped_before_playing(
        small_bag, tmp_path):
    """A replay waiting for subscribers (up to replay.wait_for_subscribers_s) said nothing
    for up to a minute, and stopped then it claimed '0 of 300 messages, 0.0 s after it
    started': it says what it waits for, and that it stopped before playing."""
    log = tmp_path / "replay.log"
    proc = rosutil.start(["-m", "neurncd_ros.nodes.replay", "--ros-args", "-p",
                          f"replay.bag:={small_bag}", "-p",
                          "replay.wait_for_subscribers_s:=120"],
                         ros_env(rosutil.domain(14)), log)
    try:
        assert _wait_for(lambda: "waiting (at most 120 s" in log.read_text(), 60), \
            log.read_text()
    finally:
        code = rosutil.stop(proc, 30)
    text = log.read_text()
    assert code == 0, text
    assert "replay stopped before playing (while waiting for subscribers" in text, text
    assert "s after it started" not in text and "replay finished" not in text, text


@pytest.fixture
def executor_node():
    """An rclpy node and a MultiThreadedExecutor of 2 threads spinning nothing yet, on a
    private domain; the executor is the test's to stop."""
    apply_ros_env(rosutil.domain(14))
    import rclpy
    from rclpy.executors import MultiThreadedExecutor

    rclpy.init()
    node = rclpy.create_node("stop_executor_test")
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    rclpy.shutdown()


def _spin_until(executor, predicate, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while not predicate() and time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    return predicate()


def _record_shutdown(executor, outcome: list) -> None:
    """Note in ``outcome`` when ``executor.shutdown`` is called."""
    shutdown = executor.shutdown

    def noted(*args, **kwargs):
        outcome.append("shutdown")
        return shutdown(*args, **kwargs)
    executor.shutdown = noted


def test_stop_executor_waits_for_callbacks_already_running(executor_node):
    """The node is destroyed only once no callback runs: rclpy's Executor.shutdown alone
    returns while one still does, which then fails on the destroyed node ("cannot use
    Destroyable because destruction was requested", printed at exit). The executor is
    shut down only after the callback ended."""
    from std_msgs.msg import String

    from neurncd_ros.nodes.common import stop_executor

    node, executor = executor_node
    pub = node.create_publisher(String, "/stop_executor_test", 1)
    entered, release = threading.Event(), threading.Event()
    outcome: list[str] = []

    def callback() -> None:
        if entered.is_set():
            return
        entered.set()
        release.wait(5)
        try:
            pub.publish(String(data="late"))
            outcome.append("published")
        except Exception as err:  # noqa: BLE001 - what the test looks for
            outcome.append(repr(err))

    node.create_timer(0.01, callback)
    assert _spin_until(executor, entered.is_set)
    _record_shutdown(executor, outcome)
    threading.Timer(0.3, release.set).start()  # goes on once the stop has begun
    try:
        stop_executor(executor, timeout_sec=5.0)
    finally:
        release.set()
    assert outcome == ["published", "shutdown"], outcome


def test_stop_executor_lets_callbacks_handed_to_its_threads_run_first(executor_node, capfd):
    """The cause of "a callback failed while stopping: InvalidHandle: cannot use
    Destroyable because destruction was requested" (one stop in three of a node fed with
    frames): a callback the executor had handed to its thread pool but that had not
    started yet triggers the executor's guard condition when it starts, which
    Executor.shutdown had destroyed. Here both threads are busy, a third callback waits
    for one, and the stop begins: it must run, and nothing fails."""
    from rclpy.callback_groups import ReentrantCallbackGroup

    from neurncd_ros.nodes.common import stop_executor

    node, executor = executor_node
    release = threading.Event()
    calls: list[int] = []

    def callback() -> None:
        calls.append(1)
        if len(calls) <= 2:
            release.wait(5)  # the pool's two threads are held

    node.create_timer(0.01, callback, callback_group=ReentrantCallbackGroup())
    queued = lambda: sum(not t.done() for t in executor._futures) >= 3  # noqa: E731
    assert _spin_until(executor, lambda: len(calls) >= 2 and queued())
    tasks = list(executor._futures)
    threading.Timer(0.3, release.set).start()
    try:
        stop_executor(executor, timeout_sec=5.0, name="stopper")
    finally:
        release.set()
    assert all(t.done() for t in tasks)
    assert [t.exception() for t in tasks if t.exception() is not None] == []
    assert len(calls) >= 3, "the callback waiting for a thread never ran"
    assert "failed while stopping" not in capfd.readouterr().err


def test_stop_executor_names_the_node_of_a_callback_that_failed(executor_node, capfd):
    """A callback failing while the node stops is reported naming the node (it was
    printed without it, so a launch of several nodes did not tell whose it was)."""
    from neurncd_ros.nodes.common import stop_executor

    node, executor = executor_node
    entered, release = threading.Event(), threading.Event()

    def callback() -> None:
        if entered.is_set():
            return
        entered.set()
        release.wait(5)
        raise RuntimeError("gave up")

    node.create_timer(0.01, callback)
    assert _spin_until(executor, entered.is_set)
    threading.Timer(0.3, release.set).start()
    try:
        stop_executor(executor, timeout_sec=5.0, name="mapper")
    finally:
        release.set()
    assert ("mapper: a callback failed while stopping: RuntimeError: gave up"
            in capfd.readouterr().err)


def test_stale_fast_dds_shared_memory_is_removed_and_live_segments_are_kept(tmp_path):
    """A segment whose lock file nobody holds (its process was killed) is removed with its
    lock and mutex; one whose lock is held (a running process) and one just created are
    kept (what bringup and the test session do to /dev/shm)."""
    import fcntl

    from neurncd_ros.nodes.process import remove_stale_shm

    def segment(name: str, age_s: float) -> Path:
        seg = tmp_path / name
        seg.write_bytes(b"\0" * 1000)
        lock = tmp_path / f"{name}_el"
        lock.touch()
        old = time.time() - age_s
        os.utime(lock, (old, old))
        return lock

    dead = segment("fastrtps_00000000000000aa", 120)
    (tmp_path / "sem.fastrtps_00000000000000aa_mutex").write_bytes(b"\0" * 32)
    live = segment("fastrtps_00000000000000bb", 120)
    young = segment("fastrtps_00000000000000cc", 1)
    fd = os.open(live, os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as the running owner holds it
    try:
        assert remove_stale_shm(tmp_path, min_age_s=60) == (1, 1032)
    finally:
        os.close(fd)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["fastrtps_00000000000000bb", "fastrtps_00000000000000bb_el",
                    "fastrtps_00000000000000cc", "fastrtps_00000000000000cc_el"]
    assert not dead.exists() and live.exists() and young.exists()


def test_a_node_that_receives_nothing_says_where_it_listens(executor_node, capfd):
    """A node whose inputs never arrive (a topic name, namespace or remap wrong) says so
    once, naming the topics as resolved and their publishers (a user audit's nodes under
    -r __ns:=/robot1 waited 55 s in silence)."""
    from neurncd_ros.nodes.common import InputWatch

    node, _ = executor_node
    import rclpy

    ns = rclpy.create_node("watched", namespace="/robot1", context=node.context)
    try:
        watch = InputWatch(ns, ["camera/color/image_raw", "/camera/depth/image_raw"],
                           after_s=0.0)
        watch.check(received=3)
        assert not watch.warned  # something arrived: nothing to say
        watch.check(received=0)
        watch.check(received=0)
    finally:
        ns.destroy_node()
    err = capfd.readouterr().err
    assert err.count("nothing received for 0 s on") == 1, err
    assert "/robot1/camera/color/image_raw (0 publishers)" in err, err
    assert "/camera/depth/image_raw (0 publishers)" in err and "topics.*" in err
    # Inputs that have publishers but send nothing (the upstream node still waiting for
    # its own inputs): the names are right, and the warning does not blame them.
    from std_msgs.msg import String
    quiet = rclpy.create_node("quiet_upstream", context=node.context)
    listener = rclpy.create_node("listener", context=node.context)
    try:
        quiet.create_publisher(String, "/upstream/quiet", 1)
        watch = InputWatch(listener, ["/upstream/quiet"], after_s=0.0)
        assert _wait_for(lambda: listener.count_publishers("/upstream/quiet"), 30)
        watch.check(received=0)
    finally:
        quiet.destroy_node()
        listener.destroy_node()
    err = capfd.readouterr().err
    assert "/upstream/quiet (1 publishers)" in err and "names are right" in err, err
    assert "topics.*" not in err, err


def test_a_node_says_when_an_input_loses_its_publisher_and_when_it_is_back(executor_node,
                                                                           capfd):
    """A killed mapper left discovery at 'running' with nothing said: an input that had a
    publisher and has none any more is logged (and counted on /diagnostics as
    inputs_without_publisher), and so is its return."""
    from std_msgs.msg import String

    from neurncd_ros.core.engine.health import Health
    from neurncd_ros.nodes.common import InputWatch

    node, executor = executor_node
    import rclpy

    watched = rclpy.create_node("watched_inputs", context=node.context)
    health = Health("watched")
    watch = InputWatch(watched, ["/upstream/view"], health=health)
    try:
        def publishers() -> int:
            return watched.count_publishers("/upstream/view")

        watch.check(received=0)  # nothing yet: not "gone"
        assert health.gauges["inputs_without_publisher"] == 0
        pub = node.create_publisher(String, "/upstream/view", 10)
        assert _spin_until(executor, lambda: publishers() == 1)
        watch.check(received=5)
        node.destroy_publisher(pub)
        assert _spin_until(executor, lambda: publishers() == 0)
        watch.check(received=5)
        assert health.gauges["inputs_without_publisher"] == 1
        pub = node.create_publisher(String, "/upstream/view", 10)
        assert _spin_until(executor, lambda: publishers() == 1)
        watch.check(received=6)
        assert health.gauges["inputs_without_publisher"] == 0
    finally:
        watched.destroy_node()
    err = capfd.readouterr().err
    assert err.count("no publisher on /upstream/view any more") == 1, err
    assert err.count("/upstream/view has a publisher again") == 1, err
