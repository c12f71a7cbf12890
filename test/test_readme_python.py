"""The README's "From Python, without ROS" block runs as written: the engine the nodes
drive, fed numpy frames from a plain Python process, labels them, and the labels score
as labels should (a README example that no longer runs is a user's first failure)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _block() -> str:
    text = (REPO / "README.md").read_text()
    start = text.index("### From Python, without ROS")
    return re.search(r"```python\n(.*?)```", text[start:], re.S).group(1)


def test_the_readme_python_block_labels_a_scene(tmp_path):
    script = tmp_path / "example.py"
    # ... and needs no ROS: nothing of it imports rclpy
    script.write_text(_block() + "\nimport sys\nassert 'rclpy' not in sys.modules, 'rclpy'\n")
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    r = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    m = re.search(r"(\d+) classes in the last frame; mIoU all ([\d.]+), known ([\d.]+), "
                  r"novel ([\d.]+)", r.stdout)
    assert m, r.stdout
    classes, known = int(m.group(1)), float(m.group(3))
    # 60 frames of a held-out scene: the known classes are labelled as the engine labels
    # them (88 at this commit; the backbone alone scores about 78 on such scenes).
    assert classes >= 5 and known >= 60.0, r.stdout
    assert not list(tmp_path.glob("out*")), "the engine alone writes no files"
