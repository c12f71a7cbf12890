"""Where the package's shared files are: share/neurncd_ros of a colcon install, or the
source tree.

Standard library only (``ament_index_python`` when it is there): the nodes locate their
DDS profile and parameter file through it before anything heavy is imported, and the
offline tool its default parameter file, in a source checkout and in an ament install
alike (where the package's own folder has no ``config/`` beside it).
"""

from __future__ import annotations

from pathlib import Path

PACKAGE = "neurncd_ros"


def share_file(*parts: str) -> Path:
    """A file of the package's share/ (colcon install) or of the source tree."""
    try:
        from ament_index_python.packages import get_package_share_directory
        path = Path(get_package_share_directory(PACKAGE)).joinpath(*parts)
        if path.exists():
            return path
    except Exception:  # not installed with colcon: fall back to the source tree
        pass
    return Path(__file__).resolve().parents[1].joinpath(*parts)
