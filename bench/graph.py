"""The live graph end to end over DDS, as a user runs it, then the same bag offline.

A 300-frame 30 Hz synthetic bag of a held-out seed (seeds.TEST, 320x240,
realistic depth) is replayed in real time by ``bringup --bag`` into the
embedding, mapper and discovery nodes, each in its own process, with a
separate recorder process subscribed to the replayed depth and to
/neurncd/labels. Latency is the wall time from the depth frame's arrival at
the recorder (on one machine over shared memory: its publication, to within a
millisecond) to the arrival of its label. Then the same bag goes through
``neurncd run`` (the offline engine) and both are scored against the bag's
ground truth.

Figures (bench/results/graph.json; shares are fractions, mIoU percent):
``label_rate_hz`` (labels per second between the first label and the end of
the bag), ``latency_median_s``, ``latency_p95_s``, ``keyframes_labelled_share``
(keyframes whose label arrived by the end of the bag + 10 s),
``frames_labelled_share``, ``mapper_frames_paired`` and ``mapper_problems`` (from
the mapper's exit line: frames whose embedding met its colour, depth and pose, and
its problems by kind, e.g. ``unpaired`` embeddings whose inputs DDS lost),
``peak_rss_gb_all_nodes`` (largest sum of the nodes'
resident memory, sampled every 0.25 s), ``cpu_share_per_node`` (CPU seconds /
wall seconds), ``mapper_iterations_per_s``, ``shutdown_s`` per node (SIGINT to
exit), ``online_miou_*`` and ``offline_miou_*``, and ``machine_probe_ms`` (the
default backbone in float32 on one 320x240 frame, 1 thread, median) to compare machines:
on a machine slower than a 40 ms probe, ``probe_scale`` = probe / 40 and the
``*_at_probe_40ms`` keys give the rate times it and the latencies divided by it.

``--poses odometry`` plays the same scene from a bag without its pose topic
(and no /tf), with ``mapper_node.pose_source`` odometry: the mapper's pose
stage tracks the frames itself and publishes /camera/pose. It writes
bench/results/graph_odometry.json and graph_odometry.png (graph.json is left
alone) with the same figures plus ``mapper_pose_summary`` (the odometry's own
count of tracked and lost frames and its ms per frame inside the mapper); the
offline comparison runs ``neurncd run``'s path for such a bag (the poses
estimated by the same odometry).

    .venv/bin/python bench/graph.py            # seed 2000, 300 frames
    .venv/bin/python bench/graph.py --frames 150 --seed 2001
    .venv/bin/python bench/graph.py --poses odometry
    .venv/bin/python bench/graph.py --sweep mapper.train_nice=0,10 --repeat 5
    .venv/bin/python bench/graph.py --size 640x480   # graph_640x480.json
    .venv/bin/python bench/graph.py --frames 5400 --no-offline   # graph_n5400.json, 3 min

``--frames N`` other than 300 plays a longer (or shorter) walk of the same scene and writes
``graph_n<N>.json`` / ``.png`` (after any ``_odometry`` / ``_<W>x<H>``), so the 300-frame
records stay: ``--frames 5400`` is three minutes, as a user replays a NYUv2 sequence. Every
run also records ``windows`` (per 30 s of the replay: labels of its frames, their latency
median and p95, each node's resident memory at the window's end) and ``rss_gb_series``
(every node's resident memory every 5 s), so a long bag shows whether latency or memory
drift; its picture adds them as a third panel.

``--size WxH`` plays the same scene at another frame size (640x480 is the size of
NYUv2, TUM and Replica): the embedding, the views and discovery cost about as the
pixels, so this is what a user replaying those datasets at their own size sees.

``--sweep SECTION.KEY=V1,V2,...`` measures only the live graph, once per value in each of
``--repeat`` rounds, the values interleaved within a round, so that the machine's drift
(rates and latencies move by a quarter between runs here) hits every value alike; it
writes ``graph_sweep_<section>_<key>.json``: every run's figures (each after its own
machine probe) and the medians per value.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import signal
import statistics
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import commit, parse_sweep  # noqa: E402  (bench/ is on sys.path)

RESULTS = REPO / "bench" / "results"
DOMAIN = 231  # default ROS_DOMAIN_ID: above the test sessions' 1..224 (--domain-id)
PROBE_REFERENCE_MS = 40.0  # the machine the rate and latency targets are set for

RECORDER = textwrap.dedent("""
    import json, sys, time
    import numpy as np
    import rclpy
    from rclpy.signals import SignalHandlerOptions
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import Image
    from neurncd_ros.core import msgconv
    from neurncd_ros.core.topics import Topics
    from neurncd_ros.nodes.common import output_qos, sensor_qos
    from neurncd_ros.nodes.process import Shutdown
    topics = Topics()
    out = sys.argv[1]
    shutdown = Shutdown().install()
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("graph_recorder")
    depth, labels, keyframes, images = {}, {}, [], {}
    def stamp(m):
        return msgconv.stamp_to_ns(m.header.stamp)
    def on_depth(m):
        depth.setdefault(stamp(m), time.monotonic())
    def on_label(m):
        s = stamp(m)
        if s not in labels:
            labels[s] = time.monotonic()
            images[s] = msgconv.image_to_array(m, topics.labels)
    node.create_subscription(Image, topics.depth, on_depth, sensor_qos(100))
    node.create_subscription(Image, topics.labels, on_label, output_qos(100))
    node.create_subscription(PoseStamped, topics.keyframes,
                             lambda m: keyframes.append(stamp(m)), output_qos(100))
    open(out + ".ready", "w").close()
    while not shutdown.requested.is_set():
        rclpy.spin_once(node, timeout_sec=0.05)
    json.dump({"depth": depth, "labels": labels, "keyframes": keyframes}, open(out, "w"))
    np.savez_compressed(out + ".npz", **{str(k): v for k, v in images.items()})
""")


def make_bag(seed: int, frames: int, poses: str = "bag",
             size: tuple[int, int] | None = None) -> Path:
    """The scene's bag (cached); ``poses`` "odometry": the same frames without a pose topic;
    ``size`` (width, height): frames of that size instead of the generator's 320x240."""
    from neurncd_ros import synth
    from neurncd_ros.core.data.bag import write_bag

    suffix = "_noposes" if poses == "odometry" else ""
    scfg = synth.SynthConfig() if size is None else synth.SynthConfig(width=size[0],
                                                                      height=size[1])
    if size is not None:
        suffix += f"_{size[0]}x{size[1]}"
    path = Path(os.environ.get("NEURNCD_GRAPH_CACHE", "/tmp/neurncd_graph")) / \
        f"graph_s{seed}_n{frames}{suffix}.mcap"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        from tqdm import tqdm
        write_bag(path, tqdm(synth.generate(seed, frames, scfg), total=frames,
                             desc=f"synth seed {seed}", unit="frame"),
                  pose_mode="none" if poses == "odometry" else "topic")
    return path


def ros_env() -> dict[str, str]:
    """The graph's environment: this machine only, its own domain id (the traffic of
    another graph on the same id would be measured with this one's)."""
    env = dict(os.environ)
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(DOMAIN),
               PYTHONUNBUFFERED="1")
    profile = str(REPO / "config" / "fastdds_shm.xml")
    env["FASTRTPS_DEFAULT_PROFILES_FILE"] = env["FASTDDS_DEFAULT_PROFILES_FILE"] = profile
    return env


def children(pid: int) -> dict[str, int]:
    """Node name -> pid of the node processes started by bringup ``pid``."""
    out = {}
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == pid:
            for part in cmd:
                if part.startswith(b"neurncd_ros.nodes."):
                    out[part.decode().rsplit(".", 1)[1]] = int(proc.name)
    return out


def rss_and_cpu(pid: int) -> tuple[float, float] | None:
    """(resident GB, CPU seconds) of a process, None once it is gone."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        stat = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    rss = [ln.split()[1] for ln in status.splitlines() if ln.startswith("VmRSS")]
    if not rss:  # a zombie: it has exited
        return None
    rss_kb = int(rss[0])
    tick = os.sysconf("SC_CLK_TCK")
    return rss_kb / 2 ** 20, (int(stat[11]) + int(stat[12])) / tick


def machine_probe_ms() -> float:
    """The default net in float32 on one 320x240 frame, one thread, median ms: a fixed
    workload to compare machines and days (float32 whatever ``backbone.precision``
    chooses, so probes taken before bfloat16 compare with those after)."""
    import torch

    from neurncd_ros import synth
    from neurncd_ros.core.backbone.backbone import BackboneConfig, load_backbone

    torch.set_num_threads(1)
    bb = load_backbone(BackboneConfig(num_threads=1, precision="float32"))
    f = next(iter(synth.generate(2000, 1, synth.SynthConfig())))
    for _ in range(3):
        bb.predict(f.rgb, f.depth)
    ts = []
    for _ in range(20):
        t = time.perf_counter()
        bb.predict(f.rgb, f.depth)
        ts.append(time.perf_counter() - t)
    return 1000 * statistics.median(ts)


def run_live(bag: Path, work: Path, extra: list[str]) -> dict:
    """Recorder + bringup; returns the recording and process figures."""
    env = ros_env()
    rec_out = work / "recording.json"
    for p in (rec_out, Path(str(rec_out) + ".ready")):
        p.unlink(missing_ok=True)
    recorder = subprocess.Popen([sys.executable, "-c", RECORDER, str(rec_out)], env=env,
                                stdout=open(work / "recorder.log", "w"),
                                stderr=subprocess.STDOUT, cwd=REPO)
    while not Path(str(rec_out) + ".ready").exists():
        if recorder.poll() is not None:
            raise SystemExit("recorder died: " + (work / "recorder.log").read_text())
        time.sleep(0.1)
    log = open(work / "bringup.log", "w")
    t0 = time.monotonic()
    bringup = subprocess.Popen([sys.executable, "-m", "neurncd_ros.nodes.bringup", "--bag",
                                str(bag), "--ros-args", *extra], env=env, stdout=log,
                               stderr=subprocess.STDOUT, cwd=REPO)
    pids: dict[str, int] = {}
    peak, cpu, first_seen, last_seen = 0.0, {}, {}, {}
    shutdown_s: dict[str, float] = {}
    series: list[tuple[float, dict[str, float]]] = []  # (monotonic time, node -> RSS GB)
    stop_sent = None
    while bringup.poll() is None:
        pids.update(children(bringup.pid))
        total, sample = 0.0, {}
        for name, pid in pids.items():
            r = rss_and_cpu(pid)
            now = time.monotonic()
            if r is None:
                if name not in shutdown_s and stop_sent is not None:
                    shutdown_s[name] = now - stop_sent
                continue
            total += r[0]
            sample[name] = r[0]
            cpu[name] = r[1]
            first_seen.setdefault(name, now)
            last_seen[name] = now
        peak = max(peak, total)
        if sample and stop_sent is None and (not series or now - series[-1][0] >= 1.0):
            series.append((now, sample))
        if stop_sent is None and "stopping" in (work / "bringup.log").read_text():
            stop_sent = time.monotonic()
        time.sleep(0.25)
    wall = time.monotonic() - t0
    recorder.send_signal(signal.SIGINT)
    recorder.wait(timeout=60)
    rec = json.loads(rec_out.read_text())
    with np.load(str(rec_out) + ".npz") as z:
        images = {int(k): z[k] for k in z.files}
    text = (work / "bringup.log").read_text()
    iterations, pose_summary, paired, problems = 0, None, None, None
    for line in text.splitlines():
        if "[mapper]" in line and "iterations" in line and "frames paired" in line:
            iterations = int(line.split("iterations ")[1].split(",")[0])
            paired = int(line.split("frames paired ")[1].split(",")[0])
            if ", problems " in line:
                problems = ast.literal_eval(line.split(", problems ", 1)[1].split("; ")[0])
            if "; pose source" in line:
                pose_summary = line.split("; pose source", 1)[1].strip(" :")
    return {"rec": rec, "images": images, "peak_rss_gb": peak, "wall_s": wall,
            "bringup_code": bringup.returncode, "log": text,
            "cpu_share": {n: round(cpu[n] / max(last_seen[n] - first_seen[n], 1e-3), 3)
                          for n in cpu},
            "shutdown_s": {n: round(v, 2) for n, v in shutdown_s.items()},
            "mapper_iterations": iterations, "pose_summary": pose_summary,
            "mapper_frames_paired": paired, "mapper_problems": problems, "rss_series": series}


def score(frames: dict, labels: dict) -> dict:
    from neurncd_ros.core.discovery.metrics import Evaluator

    ev = Evaluator()
    for stamp, lab in labels.items():
        if stamp in frames:
            ev.update(lab, frames[stamp].semantic)
    r = ev.result()
    return {k: round(r[k], 2) for k in ("miou_known", "miou_novel", "miou_all", "total_acc")}


def picture(depth: dict, labels: dict, keyframes: set, res: dict, path: Path) -> None:
    """Each labelled frame as a line from its arrival to its label's (keyframes in red),
    and the latency distribution."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = min(depth.values())
    series = res.get("rss_gb_series") or []
    long_run = len(res.get("windows", [])) > 1
    fig, axes = plt.subplots(1, 3 if long_run else 2, figsize=(16 if long_run else 12, 4),
                             gridspec_kw={"width_ratios": [3, 1, 2] if long_run else [3, 1]})
    a, b = axes[0], axes[1]
    a.plot([t - t0 for t in depth.values()], [0] * len(depth), "|", color="0.6",
           label="frame arrives")
    for s, t in labels.items():
        if s in depth:
            kf = s in keyframes
            a.plot([depth[s] - t0, t - t0], [0, 1], color="tab:red" if kf else "tab:blue",
                   lw=0.8, alpha=0.8)
    a.plot([], [], color="tab:red", label="keyframe labelled")
    a.plot([], [], color="tab:blue", label="frame labelled")
    a.set_yticks([0, 1], ["frame", "label"])
    a.set_xlabel("wall time (s)")
    a.set_title(f"live graph: {res['label_rate_hz']} labels/s, "
                f"{100 * res['frames_labelled_share']:.0f} % of frames, "
                f"{100 * res['keyframes_labelled_share']:.0f} % of keyframes")
    a.legend(loc="upper left", fontsize=8)
    lat = [labels[s] - depth[s] for s in labels if s in depth]
    b.hist(lat, bins=20, color="tab:blue")
    b.axvline(res["latency_median_s"], color="k", ls="--", label="median")
    b.axvline(res["latency_p95_s"], color="tab:red", ls=":", label="p95")
    b.set_xlabel("latency (s)")
    b.legend(fontsize=8)
    if long_run:  # memory of each node over the replay, and the latency per window
        c = axes[2]
        for node in sorted({k for _, r in series for k in r}):
            c.plot([t for t, r in series if node in r], [r[node] for _, r in series if node in r],
                   label=f"{node} RSS")
        c.set_xlabel("time since the first frame (s)")
        c.set_ylabel("resident memory (GB)")
        c2 = c.twinx()
        win = [w for w in res["windows"] if w["latency_median_s"] is not None]
        c2.plot([w["start_s"] + WINDOW_S / 2 for w in win], [w["latency_median_s"] for w in win],
                "k--o", label="latency median per window")
        c2.set_ylabel("latency (s)")
        c.legend(loc="upper left", fontsize=8)
        c2.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def live_run(bag: Path, work: Path, params: list[str], frames: dict, seed: int,
             n_frames: int, odometry: bool, probe: float) -> tuple[dict, dict, dict, set]:
    """One replay of ``bag`` through the live graph with ROS parameter overrides ``params``
    (``SECTION.KEY:=VALUE``): the figures of the module doc but the offline ones, and the
    recording (depth arrival and label arrival per stamp, the keyframes)."""
    live = run_live(bag, work, sum((["-p", s] for s in params), []))
    if live["bringup_code"] != 0:
        raise SystemExit(f"bringup failed ({live['bringup_code']}):\n{live['log'][-3000:]}")
    rec = live["rec"]
    depth = {int(k): v for k, v in rec["depth"].items()}
    labels = {int(k): v for k, v in rec["labels"].items()}
    keyframes = set(rec["keyframes"])
    bag_end = max(depth.values())
    lat = [labels[s] - depth[s] for s in labels if s in depth]
    t_lab = sorted(t for t in labels.values() if t <= bag_end)
    rate = (len(t_lab) - 1) / (t_lab[-1] - t_lab[0]) if len(t_lab) > 1 else 0.0
    kf_in_time = [s for s in keyframes if s in labels and labels[s] <= bag_end + 10.0]
    res = {
        "seed": seed, "frames": n_frames, "fps": 30,
        "size": "x".join(str(v) for v in next(iter(frames.values())).depth.shape[::-1]),
        "poses": "mapper odometry (bag without poses)" if odometry else "bag pose topic",
        "mapper_pose_summary": live["pose_summary"],
        "machine_probe_ms": round(probe, 1),
        "label_rate_hz": round(rate, 2),
        "latency_median_s": round(float(np.median(lat)), 3) if lat else None,
        "latency_p95_s": round(float(np.percentile(lat, 95)), 3) if lat else None,
        "labels": len(labels), "keyframes": len(keyframes),
        "keyframes_labelled_share": round(len(kf_in_time) / max(len(keyframes), 1), 3),
        "frames_labelled_share": round(len(labels) / len(frames), 3),
        "peak_rss_gb_all_nodes": round(live["peak_rss_gb"], 3),
        "cpu_share_per_node": live["cpu_share"],
        "shutdown_s": live["shutdown_s"],
        "mapper_iterations": live["mapper_iterations"],
        "mapper_frames_paired": live["mapper_frames_paired"],
        "mapper_problems": live["mapper_problems"],
        "mapper_iterations_per_s": round(live["mapper_iterations"] / max(
            (n_frames / 30.0), 1e-3), 2),
        "live_wall_s": round(live["wall_s"], 1),
    }
    # The targets hold on a machine whose probe is at most 40 ms; on a
    # slower one the rate and latency are scaled by the probe (CPU-bound stages).
    scale = max(probe / PROBE_REFERENCE_MS, 1.0)
    res["probe_scale"] = round(scale, 3)
    res["label_rate_hz_at_probe_40ms"] = round(rate * scale, 2)
    for k in ("latency_median_s", "latency_p95_s"):
        if res[k] is not None:
            res[f"{k}_at_probe_40ms"] = round(res[k] / scale, 3)
    res["windows"] = windows(depth, labels, live["rss_series"])
    # Every 5 s, in seconds since the replay's first frame (negative: the nodes starting).
    t_first = min(depth.values())
    res["rss_gb_series"] = [[round(t - t_first, 1), {k: round(v, 3) for k, v in r.items()}]
                            for t, r in live["rss_series"][::5]]
    online = score(frames, live["images"])
    res.update({f"online_{k}": v for k, v in online.items()})
    return res, depth, labels, keyframes


WINDOW_S = 30.0


def windows(depth: dict, labels: dict, rss_series: list) -> list[dict]:
    """The run in windows of :data:`WINDOW_S` of the bag's replay (by the arrival of the
    frames): per window the labels of its frames, their latency median and p95, and each
    node's resident memory at the window's end (the last sample in it), so that a long
    bag shows whether latency or memory drift."""
    t0 = min(depth.values())
    n = int((max(depth.values()) - t0) // WINDOW_S) + 1
    out = []
    for w in range(n):
        lo, hi = t0 + w * WINDOW_S, t0 + (w + 1) * WINDOW_S
        lat = [labels[s] - t for s, t in depth.items() if lo <= t < hi and s in labels]
        rss = [r for t, r in rss_series if t < hi]
        out.append({
            "start_s": w * WINDOW_S,
            "frames": sum(lo <= t < hi for t in depth.values()),
            "labels": len(lat),
            "latency_median_s": round(float(np.median(lat)), 3) if lat else None,
            "latency_p95_s": round(float(np.percentile(lat, 95)), 3) if lat else None,
            "rss_gb": {k: round(v, 3) for k, v in rss[-1].items()} if rss else {},
        })
    return out


SWEEP_KEYS = ("label_rate_hz", "latency_median_s", "latency_p95_s", "mapper_iterations_per_s",
              "online_miou_all", "online_miou_known", "online_miou_novel")


def sweep(bag: Path, work: Path, base: list[str], key: str, values: list[str], repeat: int,
          frames: dict, seed: int, n_frames: int, odometry: bool) -> dict:
    """The live graph once per value of ``key`` per round, ``repeat`` rounds, the values
    interleaved within each round (so the machine's drift over the runs hits every value
    alike): per value its runs (with the machine probe taken just before each) and the
    medians of :data:`SWEEP_KEYS` over them."""
    from tqdm import tqdm

    runs: dict[str, list[dict]] = {v: [] for v in values}
    with tqdm(total=repeat * len(values), desc=f"sweep {key}", unit="run") as bar:
        for _ in range(repeat):
            for v in values:
                probe = machine_probe_ms()
                res, *_ = live_run(bag, work, base + [f"{key}:={v}"], frames, seed,
                                   n_frames, odometry, probe)
                runs[v].append({k: res[k] for k in ("machine_probe_ms", "labels",
                                                    "keyframes", "cpu_share_per_node",
                                                    *SWEEP_KEYS)})
                bar.update()
    out = {"param": key, "values": values, "repeat": repeat, "seed": seed,
           "frames": n_frames, "set": base, "runs": runs,
           "median": {v: {k: float(np.median([r[k] for r in runs[v] if r[k] is not None]))
                          for k in SWEEP_KEYS + ("machine_probe_ms",)} for v in values}}
    return out


def main() -> None:
    global DOMAIN
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=None, help="default: the first test seed")
    ap.add_argument("--domain-id", type=int, default=DOMAIN,
                    help=f"ROS_DOMAIN_ID of the measured graph (default {DOMAIN}; traffic stays "
                         "on this machine): give another to run two at once")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY:=VALUE",
                    help="ROS parameter override passed to every node (-p)")
    ap.add_argument("--no-offline", action="store_true", help="skip the neurncd run part")
    ap.add_argument("--poses", choices=("bag", "odometry"), default="bag",
                    help="bag: the bag's pose topic; odometry: a bag without poses, the "
                    "mapper's pose stage tracks them (writes graph_odometry.json)")
    ap.add_argument("--sweep", metavar="SECTION.KEY=V1,V2,...",
                    help="only the live graph, once per value per round, the values "
                    "interleaved (graph_sweep_<section>_<key>.json)")
    ap.add_argument("--repeat", type=int, default=3, help="--sweep: rounds (default 3)")
    ap.add_argument("--size", metavar="WxH", default=None,
                    help="frames of this size instead of 320x240, e.g. 640x480 (the size of "
                    "NYUv2, TUM and Replica); writes graph_<W>x<H>.json / .png")
    args = ap.parse_args()
    if not 0 <= args.domain_id <= 232:
        ap.error(f"--domain-id must be in 0..232 (ROS 2 on Linux), got {args.domain_id}")
    DOMAIN = args.domain_id
    size = None
    if args.size:
        try:
            size = tuple(int(v) for v in args.size.lower().split("x"))
            assert len(size) == 2 and min(size) >= 16
        except (ValueError, AssertionError):
            raise SystemExit(f"--size {args.size}: expected WIDTHxHEIGHT, e.g. 640x480")
    from neurncd_ros import config
    from neurncd_ros.core.data.bag import FrameReader
    from neurncd_ros.synth import seeds

    if args.sweep:  # every value checked before the bag is made
        key, parsed = parse_sweep(args.sweep)
        values = [v for v, _, _ in parsed]
        if args.repeat < 1:
            raise SystemExit(f"--repeat {args.repeat}: at least 1 round")
    seed = seeds.TEST[0] if args.seed is None else args.seed
    odometry = args.poses == "odometry"
    long_run = f"_n{args.frames}" if args.frames != 300 else ""
    name = ("graph_odometry" if odometry else "graph") + (
        f"_{size[0]}x{size[1]}" if size else "") + long_run
    bag = make_bag(seed, args.frames, args.poses, size)
    work = Path("/tmp/neurncd_graph") / f"run_s{seed}{'_odometry' if odometry else ''}" \
        f"{f'_{size[0]}x{size[1]}' if size else ''}{long_run}"
    work.mkdir(parents=True, exist_ok=True)
    frames = {f.stamp_ns: f for f in FrameReader(bag, with_poses=not odometry)}
    params = (["mapper_node.pose_source:=odometry"] if odometry else []) + args.set
    if args.sweep:
        res = sweep(bag, work, params, key, values, args.repeat, frames, seed, args.frames,
                    odometry)
        res["cores"] = os.cpu_count()
        res["commit"] = commit()
        out = RESULTS / f"{name}_sweep_{key.replace('.', '_')}.json"
        RESULTS.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(res, indent=1, sort_keys=True))
        print(f"\nlive graph, seed {seed}, {args.frames} frames, {args.repeat} rounds, "
              f"medians over the rounds (each run: {', '.join(SWEEP_KEYS[:3])}):")
        print(f"  {'value':>8s} " + " ".join(f"{k[:18]:>18s}" for k in SWEEP_KEYS)
              + f" {'probe_ms':>9s}")
        for v in values:
            m = res["median"][v]
            print(f"  {v:>8s} " + " ".join(f"{m[k]:18.2f}" for k in SWEEP_KEYS)
                  + f" {m['machine_probe_ms']:9.1f}")
            for r in res["runs"][v]:
                print(f"  {'':>8s}   run: {r['label_rate_hz']:.2f} labels/s, latency median "
                      f"{r['latency_median_s']:.2f} s, p95 {r['latency_p95_s']:.2f} s, probe "
                      f"{r['machine_probe_ms']} ms")
        print(f"wrote {out}")
        return
    probe = machine_probe_ms()
    print(f"machine probe: default backbone {probe:.1f} ms per 320x240 frame (1 thread)")
    res, depth, labels, keyframes = live_run(bag, work, params, frames, seed, args.frames,
                                             odometry, probe)
    if not args.no_offline:
        from neurncd_ros.core.engine.offline import OfflineEngine

        import torch
        torch.set_num_threads(1)
        t = time.perf_counter()
        cfg = config.load()
        engine = OfflineEngine(cfg)
        stream = frames.values()
        if odometry:  # as neurncd run does for a bag without poses
            from neurncd_ros.core.odometry import with_odometry
            stream = with_odometry(stream, cfg.odometry)
        off = {o.frame.stamp_ns: o.labels.labels
               for o in engine.run(stream, total=len(frames))}
        res["offline_seconds"] = round(time.perf_counter() - t, 1)
        res["offline_labels"] = len(off)
        res.update({f"offline_{k}": v for k, v in score(frames, off).items()})
    res["cores"] = os.cpu_count()
    res["commit"] = commit()
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(res, indent=1, sort_keys=True))
    picture(depth, labels, keyframes, res, RESULTS / f"{name}.png")
    w, h = size or (320, 240)
    print(f"\nlive graph, seed {seed}, {args.frames} frames at 30 Hz, {w}x{h} "
          f"(machine probe {res['machine_probe_ms']} ms):")
    for k in ("label_rate_hz", "latency_median_s", "latency_p95_s", "probe_scale",
              "label_rate_hz_at_probe_40ms", "latency_median_s_at_probe_40ms",
              "latency_p95_s_at_probe_40ms", "keyframes", "keyframes_labelled_share",
              "frames_labelled_share", "mapper_frames_paired", "mapper_problems",
              "peak_rss_gb_all_nodes", "cpu_share_per_node",
              "mapper_iterations_per_s", "shutdown_s", "online_miou_all", "online_miou_known",
              "online_miou_novel", "offline_miou_all", "offline_miou_known",
              "offline_miou_novel", "poses", "mapper_pose_summary"):
        print(f"  {k:28s} {res.get(k)}")
    if len(res["windows"]) > 1:
        print(f"  per {WINDOW_S:.0f} s of replay: start, labels, latency median / p95 (s), "
              "resident GB per node")
        for w in res["windows"]:
            print(f"    {w['start_s']:6.0f} {w['labels']:5d} {w['latency_median_s']!s:>7s} / "
                  f"{w['latency_p95_s']!s:>7s}  "
                  + " ".join(f"{k} {v:.2f}" for k, v in sorted(w["rss_gb"].items())))
    print(f"wrote {RESULTS / (name + '.json')}")


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        main()
