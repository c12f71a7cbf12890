"""Behaviour check of a refactor: the quality figures of cheap benches before and after it.

    .venv/bin/python bench/refactor_check.py                 # the recorded check (below)
    .venv/bin/python bench/refactor_check.py --before C1 --after C2 [--after-set K=V ...]
    .venv/bin/python bench/refactor_check.py --before-results DIR --after-results DIR

Each side is a detached git worktree of its commit (in a temporary folder,
removed afterwards) in which the deterministic quick benches run with this
interpreter and their own rendering cache: ``bench/discovery.py --quick``
(segment purity, MCL, the descriptor-level MCL grid) and ``bench/ncd.py --quick
--workers 1`` (2 held-out scenes end to end, every ablation row). ``--*-set``
passes parameter overrides to a side's ncd run, so a default changed on purpose
between the commits (not by the refactor) can be set back. ``--*-results``
compares folders holding a side's ``discovery.json`` and ``ncd.json`` instead.

Every figure present on both sides is compared except timings (a shared CPU
makes them noise) and bookkeeping (commit, cores). Differences a deliberate
default change explains are named with ``--note KEY=WHY`` and counted apart.
Writes bench/results/refactor_check.json and prints the headline figures;
exits 1 if any other figure differs.

The recorded check: the second half of issue 13 (one entropy/softmax/IoU,
formats split, synth split, docstrings, ``pair_slices``, ...) started after
``d19c2c8``; in between, two deliberate changes moved defaults
(``170e721``: ``modulation.colour_weight`` 2 and ``discovery.mode_split`` on;
``5d6eeeb``: ``mcl.inflation`` 1.6 -> 1.4), which the after side sets back.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
BENCHES = ("discovery", "ncd")
BEFORE = "d19c2c8"
AFTER_SET = ("modulation.colour_weight=0", "discovery.mode_split=false", "mcl.inflation=1.6")
NOTES = {k: "the chosen row of the same grid: MCLConfig's default inflation is 1.4 after "
         "5d6eeeb (1.6 before); every row of the grid is compared on its own"
         for k in ("tune_default_ari", "tune_default_clusters", "tune_default_purity")}
NOT_QUALITY = re.compile(r"(_ms_per_frame|_ms_320x240|_s|_seconds|_peak_rss_gb)$|^(commit|cores"
                         r"|notes|quick)$")
HEADLINE = {
    "discovery": ("segment_purity", "segment_purity_no_colour", "segment_purity_geometric_only",
                  "segments_per_frame", "mcl_5k_ari", "mcl_5k_clusters", "mcl_5k_r12_ari",
                  "tune_exp6_r1.4_ari", "tune_exp6_r1.6_ari"),
    "ncd": ("neurncd_miou_all", "neurncd_miou_known", "neurncd_miou_novel",
            "neurncd_assigned_miou", "backbone_logits_miou_all", "paper_mcl_miou_all",
            "embedding_only_miou_all", "entropy_only_miou_all", "no_colour_edges_miou_all",
            "backbone_miou_known"),
}


def equal(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return a == b


def compare(before: dict, after: dict, notes: dict[str, str]) -> dict:
    """Figures on both sides: equal ones counted, differing ones listed with both values."""
    common = sorted(k for k in set(before) & set(after) if not NOT_QUALITY.search(k))
    differ = {k: {"before": before[k], "after": after[k]}
              for k in common if not equal(before[k], after[k])}
    explained = {k: dict(v, why=notes[k]) for k, v in differ.items() if k in notes}
    return {"compared": len(common), "equal": len(common) - len(differ),
            "differ_unexplained": {k: v for k, v in differ.items() if k not in notes},
            "differ_explained": explained,
            "only_before": sorted(set(before) - set(after)),
            "only_after": sorted(set(after) - set(before))}


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, check=True, capture_output=True,
                          text=True).stdout.strip()


def run_side(commit: str, sets: list[str], work: Path, benches: list[str], bar: tqdm
             ) -> tuple[Path, list[str]]:
    """Run the quick benches in a worktree of ``commit``; (folder of their JSON, commands)."""
    tree, out = work / "tree", work / "results"
    out.mkdir(parents=True)
    git("worktree", "add", "--detach", str(tree), commit)
    env = dict(os.environ, NEURNCD_NCD_CACHE=str(work / "cache"), OMP_NUM_THREADS="1")
    runs = {"discovery": ["bench/discovery.py", "--quick"],
            "ncd": ["bench/ncd.py", "--quick", "--workers", "1",
                    *[a for kv in sets for a in ("--set", kv)]]}
    commands = []
    try:
        for bench in benches:
            argv = runs[bench]
            bar.set_postfix_str(f"{commit} {bench}")
            log = work / f"{bench}.log"
            with log.open("w") as f:
                rc = subprocess.call([sys.executable, *argv], cwd=tree, env=env, stdout=f,
                                     stderr=subprocess.STDOUT)
            if rc != 0:
                raise RuntimeError(f"bench/{bench}.py at {commit} failed (exit {rc}); "
                                   f"end of its log:\n{log.read_text()[-2000:]}")
            # Quick runs write to bench/results/quick/ (older commits: to bench/results/).
            made = tree / "bench" / "results" / "quick" / f"{bench}.json"
            if not made.is_file():
                made = tree / "bench" / "results" / f"{bench}.json"
            shutil.copy(made, out / f"{bench}.json")
            commands.append(f"{' '.join(argv)} (worktree at {commit})")
            bar.update()
    finally:
        git("worktree", "remove", "--force", str(tree))
    return out, commands


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", default=BEFORE, help=f"commit before (default {BEFORE})")
    ap.add_argument("--after", default="HEAD", help="commit after (default HEAD)")
    ap.add_argument("--before-set", action="append", default=None, metavar="KEY=VALUE")
    ap.add_argument("--after-set", action="append", default=None, metavar="KEY=VALUE",
                    help="default: " + " ".join(AFTER_SET) + " with the default commits")
    ap.add_argument("--before-results", type=Path, help="compare this folder instead")
    ap.add_argument("--after-results", type=Path, help="compare this folder instead")
    ap.add_argument("--note", action="append", default=[], metavar="KEY=WHY",
                    help="a differing figure a deliberate change explains")
    ap.add_argument("--benches", nargs="+", choices=BENCHES, default=list(BENCHES),
                    help="compare only these (default: both)")
    ap.add_argument("--out", type=Path, default=RESULTS / "refactor_check.json")
    args = ap.parse_args()
    bad = [n for n in args.note if "=" not in n]
    if bad:
        ap.error(f"--note wants KEY=WHY, got {bad[0]!r}")
    for side in ("before", "after"):
        try:
            git("rev-parse", "--verify", "--quiet", getattr(args, side) + "^{commit}")
        except subprocess.CalledProcessError:
            ap.error(f"--{side} {getattr(args, side)!r} is not a commit of {REPO}")
    recorded = args.before == BEFORE and args.after == "HEAD"
    notes = {**(NOTES if recorded else {}), **dict(n.split("=", 1) for n in args.note)}
    sets = {"before": args.before_set or [],
            "after": args.after_set if args.after_set is not None else
            (list(AFTER_SET) if recorded else [])}
    res: dict = {"sides": {}, "benches": {}}
    folders = {"before": args.before_results, "after": args.after_results}
    todo = [s for s in folders if folders[s] is None]
    for side, folder in folders.items():
        for bench in args.benches if folder is not None else ():
            if not (folder / f"{bench}.json").is_file():
                print(f"error: {folder / f'{bench}.json'} does not exist (run bench/{bench}.py "
                      f"on the {side} side)", file=sys.stderr)
                return 2
    with tempfile.TemporaryDirectory(prefix="refactor_check_") as tmp, \
            tqdm(total=len(args.benches) * len(todo), desc="quick benches", unit="bench") as bar:
        for side in ("before", "after"):
            commit = git("rev-parse", "--short", getattr(args, side))
            info = {"commit": commit, "set": sets[side]}
            if folders[side] is None:
                folders[side], info["commands"] = run_side(commit, sets[side], Path(tmp) / side,
                                                           args.benches, bar)
            else:
                info["results_from"] = str(folders[side])
            res["sides"][side] = info
        for bench in args.benches:
            sides = {}
            for side in ("before", "after"):
                sides[side] = json.loads((folders[side] / f"{bench}.json").read_text())
            out = compare(sides["before"], sides["after"], notes)
            out.update({f"{s}_commit": sides[s].get("commit") for s in sides})
            out["headline"] = {k: {s: sides[s].get(k) for s in sides} for k in HEADLINE[bench]
                               if k in sides["before"] or k in sides["after"]}
            res["benches"][bench] = out
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1, sort_keys=True))

    for side, info in res["sides"].items():
        print(f"{side}: {info['commit']}" + (f", ncd --set {' '.join(info['set'])}"
                                             if info["set"] else ""))
    for bench, out in res["benches"].items():
        print(f"\n{bench}: {out['equal']} of {out['compared']} quality figures equal, "
              f"{len(out['differ_explained'])} differ as noted, "
              f"{len(out['differ_unexplained'])} differ otherwise")
        print(f"{'figure':34s} {'before':>10s} {'after':>10s}")
        for k, v in out["headline"].items():
            print(f"{k:34s} " + " ".join(f"{x:10.4g}" if isinstance(x, (int, float)) else
                                         f"{str(x):>10s}" for x in (v["before"], v["after"])))
        for k, v in {**out["differ_explained"], **out["differ_unexplained"]}.items():
            print(f"  differs: {k}: {v['before']} -> {v['after']}"
                  + (f" ({v['why']})" if "why" in v else ""))
    print(f"wrote {args.out}")
    return 1 if any(o["differ_unexplained"] for o in res["benches"].values()) else 0


if __name__ == "__main__":
    from neurncd_ros.core.text import progress_as_lines

    with progress_as_lines():  # a log file gets the bars as lines
        sys.exit(main())
