"""Behaviour check of a refactor: the quality figures of two bench runs, compared key by key.

Run the cheap deterministic benches at the commit before the refactor and at the
commit after it (each in its own worktree, each with its own rendering cache),
then compare the JSON they wrote:

    git worktree add --detach /tmp/before <commit>      # and one for the after commit
    (cd /tmp/before && NEURNCD_NCD_CACHE=/tmp/cache_before nice -n 10 python \\
        bench/discovery.py --quick && nice -n 10 python bench/ncd.py --quick --workers 1)
    .venv/bin/python bench/refactor_check.py --before DIR --after DIR [--note KEY=WHY ...]

``DIR`` holds the ``discovery.json`` and ``ncd.json`` of one side. Every figure
present on both sides is compared, except timings (a shared CPU makes them
noise) and bookkeeping (commit, cores); each differing figure is listed with
both values. A difference a deliberate change of a default explains (not the
refactor) is named with ``--note`` and counted apart. Writes
bench/results/refactor_check.json and prints a table of the headline figures.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
BENCHES = ("discovery", "ncd")
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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, required=True, help="folder of the before run")
    ap.add_argument("--after", type=Path, required=True, help="folder of the after run")
    ap.add_argument("--note", action="append", default=[], metavar="KEY=WHY",
                    help="a differing figure a deliberate change explains")
    ap.add_argument("--command", action="append", default=[], metavar="SIDE=COMMAND",
                    help="the command each side ran (recorded in the JSON)")
    ap.add_argument("--out", type=Path, default=RESULTS / "refactor_check.json")
    args = ap.parse_args()
    notes = dict(n.split("=", 1) for n in args.note)
    res: dict = {"commands": dict(c.split("=", 1) for c in args.command), "benches": {}}
    for bench in BENCHES:
        sides = {}
        for side in ("before", "after"):
            path = getattr(args, side) / f"{bench}.json"
            if not path.is_file():
                print(f"error: {path} does not exist (run bench/{bench}.py on that side)",
                      file=sys.stderr)
                return 2
            sides[side] = json.loads(path.read_text())
        out = compare(sides["before"], sides["after"], notes)
        out.update({f"{s}_commit": sides[s].get("commit") for s in sides})
        out["headline"] = {k: {s: sides[s].get(k) for s in sides} for k in HEADLINE[bench]
                           if k in sides["before"] or k in sides["after"]}
        res["benches"][bench] = out
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1, sort_keys=True))

    for bench, out in res["benches"].items():
        print(f"\n{bench}: {out['before_commit']} -> {out['after_commit']}: {out['equal']} of "
              f"{out['compared']} quality figures equal, {len(out['differ_explained'])} "
              f"differ as noted, {len(out['differ_unexplained'])} differ otherwise")
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
    sys.exit(main())
