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
    """A file of the running package's own tree: the source tree beside it (a checkout,
    an editable install: edits apply), else its own install prefix's share/neurncd_ros
    (``<prefix>/lib/pythonX.Y/site-packages/neurncd_ros``: colcon, pip), else the ament
    index's; the source tree's path when none holds it. The package's own copy first, so
    that code and its files never come from two installs (a stale workspace on
    AMENT_PREFIX_PATH)."""
    here = Path(__file__).resolve()
    source = here.parents[1].joinpath(*parts)
    if source.exists():
        return source
    if len(here.parents) > 4:
        own = here.parents[4].joinpath("share", PACKAGE, *parts)
        if own.exists():
            return own
    try:
        from ament_index_python.packages import get_package_share_directory
        path = Path(get_package_share_directory(PACKAGE)).joinpath(*parts)
        if path.exists():
            return path
    except Exception:  # not on the ament index
        pass
    return source
