"""Where packml_ros2's data files are, in a source checkout and when installed (colcon / pip)."""

from __future__ import annotations

import sys
from pathlib import Path

PACKAGE = "packml_ros2"


def share_dir() -> Path:
    """The package's share directory: the repository root in a checkout (editable install),
    ``<prefix>/share/packml_ros2`` when installed: first the prefix this module is installed in
    (``<prefix>/lib/pythonX.Y/site-packages/packml_ros2``, colcon's and pip's layout), then the
    ament prefixes, then the interpreter's."""
    here = Path(__file__).resolve()
    source_root = here.parents[1]
    if (source_root / "package.xml").exists() and (source_root / "config").is_dir():
        return source_root
    own = [here.parents[4]] if len(here.parents) > 4 else []
    for prefix in (*own, *(Path(p) for p in _ament_prefixes()), Path(sys.prefix)):
        candidate = prefix / "share" / PACKAGE
        if (candidate / "config").is_dir():
            return candidate
    return source_root


def _ament_prefixes() -> list[str]:
    import os

    return [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]


def config_dir() -> Path:
    return share_dir() / "config"


def fastdds_profile() -> Path:
    """The Fast DDS profile for quick, predictable discovery (config/fastdds_localhost.xml)."""
    return config_dir() / "fastdds_localhost.xml"
