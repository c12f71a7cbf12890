"""Shared by the benchmark scripts (not a benchmark itself: `neurncd bench` skips it)."""

from __future__ import annotations

import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def results_dir(quick: bool) -> Path:
    """Where a benchmark writes: bench/results, or bench/results/quick for a ``--quick``
    smoke run (it must never replace the full results the README quotes)."""
    return REPO / "bench" / "results" / ("quick" if quick else "")


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _head_at_start() -> str:
    head = _git("rev-parse", "--short", "HEAD")
    if not head:
        return "uncommitted"
    changed = _git("status", "--porcelain", "--untracked-files=no")
    return f"{head}-dirty" if changed else head


# Taken when a benchmark starts (it imports this module first): a commit made while it
# runs (a long bench beside other work) is not the code it measured.
_AT_START = _head_at_start()


def commit() -> str:
    """Short hash of HEAD when the benchmark started, ``<hash>-dirty`` when tracked files
    had uncommitted changes then, or 'uncommitted' outside a git checkout."""
    return _AT_START


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
