"""Shared by the benchmark scripts (not a benchmark itself: `neurncd bench` skips it)."""

from __future__ import annotations

import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def commit() -> str:
    """Short hash of HEAD, or 'uncommitted' when there is none."""
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                             capture_output=True, text=True, timeout=10)
        return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() \
            else "uncommitted"
    except (OSError, subprocess.SubprocessError):
        return "uncommitted"
