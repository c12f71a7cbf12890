"""Shared by the benchmark scripts (not a benchmark itself: `neurncd bench` skips it)."""

from __future__ import annotations

import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def results_dir(quick: bool) -> Path:
    """Where a benchmark writes: bench/results, or bench/results/quick for a ``--quick``
    smoke run (it must never replace the full results the README quotes)."""
    return REPO / "bench" / "results" / ("quick" if quick else "")


def commit() -> str:
    """Short hash of HEAD, or 'uncommitted' when there is none."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                             capture_output=True, text=True, timeout=10)
        return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() \
            else "uncommitted"
    except (OSError, subprocess.SubprocessError):
        return "uncommitted"


def parse_sweep(spec: str) -> tuple[str, list[tuple[str, dict, object]]]:
    """A benchmark's ``--sweep SECTION.KEY=V1,V2,...``: the key and, per value, its text,
    its override and the configuration it gives. Every value is checked against the schema
    here, before any run, so a bad one stops the benchmark at once, naming it, rather
    than minutes later in a node or a worker."""
    from neurncd_ros import config

    key, sep, raw = spec.partition("=")
    if not sep or "." not in key or not raw:
        raise SystemExit(f"--sweep {spec!r}: expected SECTION.KEY=V1,V2,...")
    out = []
    for v in raw.split(","):
        over = config.parse_overrides([f"{key}={v}"])
        try:
            out.append((v, over, config.load(None, over)))
        except config.ConfigError as err:
            raise SystemExit(f"--sweep {spec!r}: {err}") from None
    return key, out
