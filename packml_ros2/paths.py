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


def fastdds_profile(discovery_range: str = "") -> Path:
    """The Fast DDS profile for quick, predictable discovery (config/fastdds_localhost.xml); for
    ``discovery_range`` LOCALHOST, the one that also keeps every transport on this host
    (config/fastdds_loopback.xml: UDPv4 on 127.0.0.1 and shared memory): the discovery range
    alone leaves the sockets listening on every interface, and a host that names this one as a
    static peer (ROS_STATIC_PEERS) discovered and commanded the cell."""
    if discovery_range.strip().upper() == "LOCALHOST":
        return config_dir() / "fastdds_loopback.xml"
    return config_dir() / "fastdds_localhost.xml"
