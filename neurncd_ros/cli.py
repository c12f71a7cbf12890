"""`neurncd`: the offline tool. Everything the nodes do, on files, without DDS.

Subcommands: synth, convert, info, recover, train-backbone, run, eval, report, demo,
params, bench. Each long job shows progress and ends with a short summary. The module
stays one module (over 500 lines): every command is a thin body over the core beside
its parser entry, and one file shows a user every command and option.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
import warnings
from pathlib import Path


from . import config as config_mod
from .core.params import ConfigError
from .core.text import plural, progress_as_lines

REPO = Path(__file__).resolve().parents[1]


def load_config(args: argparse.Namespace) -> config_mod.Config:
    """The configuration a subcommand runs with: ``--config`` file, then ``--set`` overrides."""
    return config_mod.load(getattr(args, "config", None),
                           config_mod.parse_overrides(getattr(args, "set", None)))


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", default=None,
                   help="ROS 2 parameter file (default: the shipped config/neurncd.yaml)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE",
                   help="override one parameter, e.g. --set mapper.backend=reference")


# ------------------------------------------------------------------ commands

def update_docs() -> None:
    """Regenerate config/neurncd.yaml and the README's parameter table from the schema."""
    (REPO / "config" / "neurncd.yaml").write_text(config_mod.to_yaml(config_mod.default()))
    readme = REPO / "README.md"
    text = readme.read_text()
    start, end = "<!-- params:start -->\n", "<!-- params:end -->"
    i, j = text.index(start) + len(start), text.index(end)
    readme.write_text(text[:i] + config_mod.markdown_table() + text[j:])


def cmd_params(args: argparse.Namespace) -> int:
    if args.update_docs:
        update_docs()
        print("updated config/neurncd.yaml and the README parameter table")
    elif args.format == "markdown":
        sys.stdout.write(config_mod.markdown_table())
    else:
        sys.stdout.write(config_mod.to_yaml(load_config(args)))
    return 0


def cmd_check_config(args: argparse.Namespace) -> int:
    from .core.backbone.backbone import setup_problems

    views = [n if n.startswith("/") else "/" + n for n in args.node or []] or [None]
    # None: every node entry merged, the offline tool's view
    found: dict[str, list[str]] = {}  # error -> the nodes given the value
    for node in views:
        listed = config_mod.problems(args.file, node)
        if len(listed) <= 1:  # one error (or one tying sections): as load names it
            try:
                cfg = config_mod.load(args.file, node=node)
                listed = []
                if config_mod.checks_backbone(node):  # the embedding node's refusal
                    listed = [f"{args.file}: backbone: {text}"
                              for text in setup_problems(cfg.backbone)]
            except ConfigError as err:
                listed = [str(err)]
        for text in listed:  # every one, so that one run shows what to fix
            found.setdefault(text, []).extend([node] if node else [])
    for text, nodes in found.items():
        named = f" (node {', '.join(nodes)})" if nodes else ""
        print(f"neurncd check-config: configuration error: {text}{named}", file=sys.stderr)
    if len(found) > 1:
        print(f"{args.file}: {len(found)} errors", file=sys.stderr)
    if found:
        return 2
    n = len(cfg.to_flat())
    print(f"{args.file}: valid ({n} parameters in {len(cfg.sections)} sections"
          + (f"; for {', '.join(views)}" if args.node else "") + ")")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from . import synth
    from .core.params import build, to_dict

    cfg = load_config(args)
    scfg = build(type(cfg.synth), {**to_dict(cfg.synth),
                                   **({"width": args.width} if args.width else {}),
                                   **({"height": args.height} if args.height else {})},
                 prefix="synth.")
    out = Path(args.out)
    fmt = args.format
    if fmt != "replica":
        from .core.data.bag import storage_for
        fmt = storage_for(out, fmt)  # a suffix naming the other storage is refused here
    if out.exists() and not args.overwrite:  # before the progress bar starts
        print(f"neurncd synth: error: {out}: exists already; remove it, or overwrite it "
              "(--overwrite)", file=sys.stderr)
        return 1
    t0 = time.perf_counter()
    frames = synth.generate(args.seed, args.frames, scfg)
    frames = _progress(frames, args.frames, f"synth seed {args.seed}")
    if fmt == "replica":
        from .core.data.formats import write_replica
        n = write_replica(out, frames, overwrite=args.overwrite)
    else:
        from .core.data.bag import write_bag
        n = write_bag(out, frames, storage=fmt, topics=cfg.topics, overwrite=args.overwrite)
    print(f"wrote {plural(n, 'frame')} of seed {args.seed} ({scfg.width}x{scfg.height}, "
          f"depth noise {scfg.depth_noise}) to {out} as {fmt} in "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from .core.data import formats
    from .core.params import to_dict

    cfg = load_config(args)
    opts = config_mod.parse_overrides(args.opt, "--opt")
    folder_opts = {k: v for k, v in to_dict(cfg.convert).items()
                   if v != getattr(formats.FolderConfig(), k)}
    t0 = time.perf_counter()
    report: dict = {}
    # A bag source is read with topics.* and sync.* as info and run read it.
    n = formats.convert(args.src, args.out, kind=args.kind, storage=args.storage,
                        tf_parent=args.tf_parent, tf_child=args.tf_child, progress=True,
                        to=args.to, poses=args.poses, odometry=cfg.odometry, report=report,
                        overwrite=args.overwrite, topics=cfg.topics, sync=cfg.sync,
                        **{**folder_opts, **opts})
    print(f"converted {plural(n, 'frame')} from {args.src} to {args.out} ({args.to}) in "
          f"{time.perf_counter() - t0:.1f} s")
    if report:
        print(f"poses from RGB-D odometry: {plural(report['frames_in'], 'frame')} tracked, "
              f"{report['lost']} lost (left out), {report['relocalised']} relocalised, "
              f"{report['segments']} map segment(s)")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from .core.data.bag import FrameReader

    import numpy as np

    from .core.data.folder_common import PLAUSIBLE_MEDIAN_DEPTH_M, measured_depth

    from .core.engine.offline import bag_poses

    cfg = load_config(args)
    # A bag without poses is read as `neurncd run` reads it: its frames, poses to estimate.
    poses = bag_poses(args.bag, cfg)
    reader = FrameReader.from_config(args.bag, cfg.topics, cfg.sync, with_poses=poses == "bag")
    n, with_gt, first = 0, 0, None
    medians, valid = [], []
    for frame in reader:
        first = first or frame
        n += 1
        with_gt += frame.semantic is not None
        med, share = measured_depth(frame.depth)
        valid.append(share)
        if med is not None:
            medians.append(med)
    print(f"{args.bag}: {plural(n, 'synchronised frame')}")
    if first is not None:
        i = first.intrinsics
        print(f"  size {i.width}x{i.height}, fx {i.fx:.1f} fy {i.fy:.1f} cx {i.cx:.1f} cy "
              f"{i.cy:.1f}, semantic ground "
              f"truth in {with_gt} of {n} frames")
        # A wrong depth scale shows here first: an indoor scene is metres away.
        med = float(np.median(medians)) if medians else float("nan")
        print(f"  depth: median {med:.2f} m (median over frames of each frame's median), "
              f"{100 * float(np.median(valid)):.0f} % of pixels measured (median)")
        lo, hi = PLAUSIBLE_MEDIAN_DEPTH_M
        if not lo <= med <= hi:
            print(f"  warning: a median depth of {med:.2f} m is no indoor scene ({lo:g}-{hi:g} "
                  "m): check the depth scale the bag was made with")
    print("  " + reader.summary())
    if poses != "bag":
        print(f"  no pose in the bag ({cfg.topics.pose}, or /tf with sync.tf_parent and "
              "tf_child): `neurncd run` and the mapper node estimate them by RGB-D odometry; "
              "`neurncd convert --poses odometry` writes them into a new bag")
    return 0


def cmd_recover(args: argparse.Namespace) -> int:
    from .core.data.bag import bag_topics
    from .core.data.mcap_recover import recover_mcap
    from .core.data.sqlite_recover import is_sqlite, recover_sqlite

    out, src = Path(args.out), Path(args.bag)
    if out.exists() and not args.overwrite and not (src.exists() and out.samefile(src)):
        raise ValueError(f"{out} exists (--overwrite replaces it)")
    # Both refuse an --out that is the recording itself.
    sqlite = is_sqlite(src)
    kept = recover_sqlite(src, out) if sqlite else recover_mcap(src, out)
    topics = bag_topics(out)
    n = sum(count for _, count in topics.values())
    if sqlite:
        what = (f"messages {kept['first_id']}-{kept['last_id']}, "
                + (f"{kept['missing']} between them lost or damaged"
                   if kept["missing"] else "none missing between them")
                + (f"; {plural(kept['unreadable'], 'message')} whose data pages are lost"
                   if kept["unreadable"] else "")
                + (f"; {plural(kept['dropped'], 'message')} of no listed topic dropped"
                   if kept["dropped"] else "")
                + "; any after the last were cut off or damaged")
    else:
        what = (f"{kept['bytes']} of {kept['size']} bytes ({plural(kept['chunks'], 'whole chunk')})"
                "; the cut-off record after them is dropped")
    print(f"recovered {plural(n, 'message')} on {plural(len(topics), 'topic')} from "
          f"{args.bag} into {out}: {what}. Check it with: neurncd info {out}")
    return 0


def cmd_train_backbone(args: argparse.Namespace) -> int:
    from .tools import train_backbone
    return int(train_backbone.main(args) or 0)


def _set_threads(cfg: config_mod.Config) -> None:
    """This process runs the backbone and the mapper in turn: the mapper's thread count."""
    import torch

    if cfg.mapper.num_threads > 0:
        torch.set_num_threads(cfg.mapper.num_threads)


def cmd_run(args: argparse.Namespace) -> int:
    from .core.engine import offline

    cfg = load_config(args)
    _set_threads(cfg)
    result = offline.run_bag(args.bag, cfg, out_dir=args.out or cfg.run.out_dir)
    print(offline.summary(result))
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    """``neurncd eval``: the paper's tables (and ablations, baselines) over bags with GT."""
    from .core.eval import evaluate

    cfg = load_config(args)
    _set_threads(cfg)
    for b in args.bag:  # every bag checked before minutes are spent on the first
        evaluate.check_bag(b, cfg)
    per_bag = [evaluate.evaluate_bag(b, cfg, ablation=args.ablation, baselines=args.baselines)
               for b in args.bag]
    result = evaluate.write_eval(args.out, per_bag)
    print(evaluate.summary(result))
    print(evaluate.written(args.out, result))
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from .core.eval import report

    print(f"wrote {report.render(args.dir)}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """``make demo``: a held-out synthetic scene written as a bag, then the engine on it."""
    import shutil

    from . import synth
    from .core.data.bag import write_bag
    from .core.engine import offline

    cfg = load_config(args)
    _set_threads(cfg)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    bag = out / "scene.mcap"
    if bag.exists():
        shutil.rmtree(bag) if bag.is_dir() else bag.unlink()
    t0 = time.perf_counter()
    frames = _progress(synth.generate(args.seed, args.frames, cfg.synth), args.frames,
                       f"synth seed {args.seed}")
    n = write_bag(bag, frames, storage="mcap", topics=cfg.topics)
    print(f"demo: wrote synthetic scene seed {args.seed}, {n} frames, to {bag} in "
          f"{time.perf_counter() - t0:.1f} s")
    result = offline.run_bag(bag, cfg, out)
    result["demo_seed"] = args.seed
    print(offline.summary(result))
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    if not (REPO / "bench").is_dir():
        print(f"neurncd bench: error: no bench/ beside the package ({REPO}): the benchmarks "
              "live in the source tree; run them from a clone", file=sys.stderr)
        return 2
    scripts = sorted((REPO / "bench").glob("*.py"))
    known = [s.stem for s in scripts if not s.name.startswith("_")]
    scripts = [s for s in scripts if not s.name.startswith("_") and
               (not args.names or s.stem in args.names)]
    unknown = [n for n in args.names if n not in known]
    if unknown:  # a mistyped name among others was skipped in silence
        print(f"neurncd bench: error: no benchmark matched {unknown}; there are "
              f"{', '.join(known)}", file=sys.stderr)
        return 2
    extra = ["--quick"] if args.quick else []
    skipped = []
    if args.quick:  # a benchmark without a quick mode would refuse --quick: left out
        skipped = [s.stem for s in scripts if 'add_argument("--quick"' not in s.read_text()]
        scripts = [s for s in scripts if s.stem not in skipped]
        if args.names and skipped:
            one = len(skipped) == 1
            print(f"neurncd bench: error: {', '.join(skipped)} {'has' if one else 'have'} no "
                  f"--quick mode; run {'it' if one else 'them'} without --quick",
                  file=sys.stderr)
            return 2
        if skipped:
            print(f"neurncd bench --quick: leaving out {', '.join(skipped)} (no quick mode; "
                  "run them by name without --quick)", flush=True)
    failed = []
    for s in scripts:
        print(f"== bench/{s.name}", flush=True)
        if subprocess.call([sys.executable, str(s), *extra], cwd=REPO) != 0:
            failed.append(s.name)
    print(f"benchmarks: {len(scripts) - len(failed)} ran, {len(failed)} failed"
          + (f" {failed}" if failed else "")
          + (f", {len(skipped)} without a quick mode left out ({', '.join(skipped)})"
             if skipped else "")
          + f"; results in bench/results/{'quick/' if extra else ''}")
    return 1 if failed else 0


def _run_layout() -> str:
    """The output folder layout of ``neurncd run`` (for its --help)."""
    from .core.engine.offline import OUTPUT_LAYOUT
    return OUTPUT_LAYOUT


def _progress(it, total: int, desc: str):
    """A frame bar, cleared at its end on a terminal; in a log file its n/n line stays."""
    from tqdm import tqdm
    return tqdm(it, total=total, desc=desc, unit="frame", leave=not sys.stderr.isatty())


# ------------------------------------------------------------------ parser

def _positive_int(text: str) -> int:
    """argparse type: an integer of at least 1 (a scene of 0 frames is no bag to run)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value



def build_parser() -> argparse.ArgumentParser:
    """The ``neurncd`` argument parser with one subparser per subcommand."""
    parser = argparse.ArgumentParser(
        prog="neurncd", description="NeurNCD offline tool: synthetic scenes, dataset "
        "conversion, backbone training, the full pipeline on a bag, and benchmarks.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("params", help="print every parameter (YAML with docs, or the "
                       "README's markdown table)")
    p.add_argument("--format", choices=("yaml", "markdown"), default="yaml")
    p.add_argument("--update-docs", action="store_true",
                   help="rewrite config/neurncd.yaml and the README table (developers)")
    _add_config_args(p)
    p.set_defaults(func=cmd_params)

    p = sub.add_parser("check-config", help="validate a parameter file")
    p.add_argument("file")
    p.add_argument("--node", action="append", metavar="FQN",
                   help="check what the node of this fully qualified name (/mapper, "
                        "/robot1/embedding) is given, as rcl gives it /** and its own "
                        "entries; repeat for several nodes (default: every entry merged, "
                        "as neurncd run reads the file)")
    p.set_defaults(func=cmd_check_config)

    p = sub.add_parser("synth", help="generate a synthetic RGB-D scene with ground truth")
    p.add_argument("--seed", type=int, required=True)
    p.add_argument("--frames", type=_positive_int, default=300)
    p.add_argument("--out", required=True, help="bag path (mcap/sqlite3) or Replica folder")
    p.add_argument("--format", choices=("mcap", "sqlite3", "replica"), default=None,
                   help="default: sqlite3 for an --out ending in .db3, else mcap")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output (only once the new one is complete)")
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--height", type=int, default=None)
    _add_config_args(p)
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("convert", help="convert a dataset folder or a /tf bag into a bag "
                       "in the topic contract",
                       description="Convert a dataset folder or a bag into a bag in the "
                       "topic contract (or a Replica / TUM folder). A bag source is read "
                       "as info and run read it: its topic names are the topics.* "
                       "parameters (--config, --set topics.color=/camera/camera/color/"
                       "image_raw), its /tf pose frames sync.tf_parent / sync.tf_child or "
                       "--tf-parent / --tf-child. The output bag always has the topic "
                       "contract's default names (neurncd params lists them), so it is read "
                       "without topics.* overrides.")
    p.add_argument("src")
    p.add_argument("--out", required=True)
    p.add_argument("--kind", default="auto",
                   help="auto, replica, tum, nyu (NYUv2 raw scene folder), posetxt, redwood, "
                   "or bag")
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default=None,
                   help="bag storage; default: sqlite3 for an --out ending in .db3, else mcap")
    p.add_argument("--to", choices=("bag", "replica", "tum"), default="bag",
                   help="output: a bag (default), a Replica-layout folder or a TUM folder")
    p.add_argument("--poses", choices=("source", "odometry"), default="source",
                   help="source: the input's own poses; odometry: estimate them from the "
                   "images (odometry.* parameters), for inputs without poses")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing output (bag, Replica or TUM folder) once the new "
                   "one is complete: a conversion that fails leaves the old one as it was")
    p.add_argument("--tf-parent", default=None, help="with a /tf bag: the world frame "
                   "(replaces sync.tf_parent)")
    p.add_argument("--tf-child", default=None, help="with a /tf bag: the camera frame "
                   "(replaces sync.tf_child)")
    p.add_argument("--opt", action="append", metavar="KEY=VALUE",
                   help="reader option (a convert.* parameter), e.g. --opt depth_scale=5000 "
                   "--opt 'intrinsics=[525, 525, 319.5, 239.5]'")
    _add_config_args(p)
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("info", help="summarise a bag: synchronised frames and drops")
    p.add_argument("bag")
    _add_config_args(p)
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("recover", help="copy the part of a cut-off or damaged recording "
                       "(killed recorder, full disk, interrupted copy) that can be read into "
                       "a new file: an MCAP one into a .mcap, an SQLite one into a .db3")
    p.add_argument("bag", help="the damaged .mcap or .db3 file, or its bag folder")
    p.add_argument("--out", required=True, help="the new .mcap (or .db3) file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    p.set_defaults(func=cmd_recover)

    p = sub.add_parser("train-backbone", help="train the default RGB-D backbone on "
                       "synthetic scenes (9 known classes, novel masked out)")
    from .tools import train_backbone
    train_backbone.add_arguments(p)
    p.set_defaults(func=cmd_train_backbone)

    p = sub.add_parser("run", help="run backbone, mapper and discovery on a bag without "
                       "DDS; writes the label images, evaluates if the bag carries ground "
                       "truth", formatter_class=argparse.RawDescriptionHelpFormatter,
                       description="Run the backbone, the mapper and discovery on a bag "
                       "as the live graph does (no DDS).\nEvery labelled frame's label "
                       "image is written; a bag with ground truth\n"
                       "(/camera/semantic/image_raw) is also evaluated, a bag without is "
                       "not\n(metrics.json says \"evaluated\": false).",
                       epilog=_run_layout())
    p.add_argument("--bag", required=True)
    p.add_argument("--out", default=None, help="output folder (default run.out_dir)")
    _add_config_args(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("eval", help="the paper's Tables 1-2 (3 with --ablation) on bags with "
                       "ground truth "
                       "(runs the engine offline once per bag)")
    p.add_argument("--bag", action="append", required=True,
                   help="bag with /camera/semantic/image_raw (repeat for several); "
                   "labelled frames without a ground-truth image are left out of the scores "
                   "(eval.json: frames_evaluated of labelled)")
    p.add_argument("--ablation", action="store_true", help="add Table 3's ablation rows")
    p.add_argument("--baselines", action="store_true",
                   help="add the explicit-map baseline and Semantic-NeRF label propagation at "
                   "semnerf.label_fractions of each keyframe's pixels")
    p.add_argument("--out", required=True)
    _add_config_args(p)
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("report", help="one self-contained HTML page from an eval folder")
    p.add_argument("dir")
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("demo", help="make a synthetic scene and run the whole pipeline on "
                       "it; writes metrics, label images and overlays")
    p.add_argument("--out", default="out/demo")
    p.add_argument("--seed", type=int, default=1001)
    p.add_argument("--frames", type=_positive_int, default=300)
    _add_config_args(p)
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("bench", help="run benchmarks (bench/*.py); each writes "
                       "bench/results/<name>.json")
    p.add_argument("names", nargs="*", help="benchmark names (default: all; hours on 2 cores)")
    p.add_argument("--quick", action="store_true", help="each benchmark's smoke run, written "
                   "to bench/results/quick/ (a script without --quick refuses it)")
    p.set_defaults(func=cmd_bench)
    for sp in sub.choices.values():  # an unknown option is named with its command's usage
        sp.set_defaults(command_parser=sp)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``neurncd``: run one subcommand, return its exit code."""
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        args.command_parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    _log_above_progress_bars()
    with warnings.catch_warnings(), progress_as_lines():
        # The engine's advice (a threshold tuned for another backbone, a suspicious depth
        # scale) as a plain line, not Python's warning with its file and source line.
        warnings.showwarning = lambda message, *_a, **_k: print(
            f"neurncd {args.command}: warning: {message}", file=sys.stderr)
        return _run(args)


def _log_above_progress_bars() -> None:
    """Log records (a frame the odometry lost, each with its reason) as whole lines above
    the progress bar, through tqdm.write, not glued to the bar's line."""
    import logging

    from tqdm import tqdm

    class TqdmHandler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            tqdm.write(self.format(record), file=sys.stderr)

    root = logging.getLogger()
    if not any(h.get_name() == "neurncd-tqdm" for h in root.handlers):  # main() again
        handler = TqdmHandler(logging.WARNING)
        handler.set_name("neurncd-tqdm")
        handler.setFormatter(logging.Formatter("%(message)s"))
        root.addHandler(handler)


def _run(args: argparse.Namespace) -> int:
    try:
        return args.func(args)
    except ConfigError as err:
        print(f"neurncd {args.command}: configuration error: {err}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError) as err:
        print(f"neurncd {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
