"""What a PackML bag holds: the topics of a unit, their types and QoS, and a rosbags typestore
with the installed ``packml_interfaces`` definitions (so bags carry their type definitions and
other rosbag2 tools can read them)."""

from __future__ import annotations

import functools
import json
import os
import sys
from pathlib import Path
from typing import Any

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .. import qos
from ..ros import interface

#: The unit's outputs (:data:`.interface.Role.OUTPUT`), compared by replay (in the order a report
#: looks at them).
OUTPUT_TOPICS = ("transitions", "status", "alarms", "admin")
#: Outputs a unit publishes at its start and keeps latched (depth 1): a recorder matched on them
#: has their newest message.
LATCHED_OUTPUTS = ("status", "admin", "alarms")
#: What the unit was given: the engine's input log (replayed offline), EM reports (replayed live),
#: the configuration the unit was started with, and the engine state when the recorder joined
#: (replay starts from it when the input log does not reach back to the unit's start).
INPUT_TOPICS = ("input_log", "em_reports", "config", "snapshot")
#: What follows from the outputs (:data:`.interface.Role.DERIVED`): recorded, not compared (the
#: changeover orders follow from the inputs the log has, the stack light from the status).
DERIVED_TOPICS = ("recipe", "stack_light")
#: The unit's topics a recording holds (:mod:`..ros.interface`, ``recorded``): topic (relative to
#: ``/<cell>/<unit>``) -> ROS type name.
UNIT_TOPICS: dict[str, str] = {t.name: t.type_name for t in interface.TOPICS if t.recorded}
CELL_STATUS_TYPE = "packml_interfaces/msg/CellStatus"
#: Publisher QoS of each recorded topic (the unit's: :mod:`..ros.interface`), stored in the bag's
#: metadata.
PUBLISHER_QOS: dict[str, QoSProfile] = {
    **{name: interface.TOPIC[name].qos for name in UNIT_TOPICS},
    "coordinator": qos.CELL_STATUS,
    "line_input_log": qos.LINE_INPUT_LOG,  # the line's topics: packml_ros2.bag.line
    "line_episodes": qos.LINE_EPISODES,
    "line_losses": qos.LINE_LOSSES,
}
#: Key of the recorder's notes in the bag's ``custom_data`` (metadata.yaml).
CUSTOM_KEY = "packml"
#: What metadata.yaml says the bag was recorded on (rosbag2 writes the distribution's name: the
#: ``ROS_DISTRO`` of a sourced installation); the interfaces here are Kilted's.
DEFAULT_ROS_DISTRO = "kilted"


def ros_distro() -> str:
    return os.environ.get("ROS_DISTRO", "").strip() or DEFAULT_ROS_DISTRO


STORAGES = ("mcap", "sqlite3")


def open_writer(path: Path, storage: str = "mcap") -> Any:
    """A new rosbags ``Writer`` at ``path``, opened: rosbag2 bag version 9; mcap with its chunks
    compressed (zstd, as rosbag2's ``zstd_fast`` preset: readers decompress them transparently;
    admin data and alarm lists repeat a lot, a recording shrinks about 20 times), or sqlite3."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

    if storage not in STORAGES:
        raise ValueError(f"storage {storage!r}: choose one of {', '.join(STORAGES)}")
    mcap = storage == "mcap"
    writer = Writer(
        path, version=9, storage_plugin=StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
    )
    if mcap:
        writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    writer.open()
    return writer


def close_writer(writer: Any) -> None:
    """Close a rosbags ``Writer`` (index, metadata.yaml) with the distribution's name where
    rosbags writes its own ("ros_distro: rosbags"), in metadata.yaml and in the storage file's
    copy of it, as rosbag2 does."""
    storage = writer.storage
    close = storage.close
    line = f"ros_distro: {ros_distro()}"

    def close_storage(version: int, metadata: str) -> None:
        close(version, metadata.replace("ros_distro: rosbags", line))

    storage.close = close_storage
    writer.close()
    meta = Path(writer.metapath)
    meta.write_text(meta.read_text("utf-8").replace("ros_distro: rosbags", line), "utf-8")


def reader_qos(topic: str) -> QoSProfile:
    """The recorder's subscription: the publisher's durability (transient local history reaches
    a late recorder) with a deep reader history, so bursts are not dropped on our side."""
    pub = PUBLISHER_QOS[topic]
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max(pub.depth, 1000),
        reliability=ReliabilityPolicy.RELIABLE,
        durability=pub.durability,
    )


def msg_class(type_name: str) -> Any:
    """The rclpy message class of ``pkg/msg/Name``."""
    import importlib

    pkg, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def interface_dir() -> Path:
    """The installed ``packml_interfaces/msg`` directory (.msg files), or the checkout's."""
    candidates = [Path(sys.prefix)]
    candidates += [Path(p) for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    try:
        import packml_interfaces

        # <prefix>/lib/pythonX.Y/site-packages/packml_interfaces -> <prefix>
        candidates.append(Path(packml_interfaces.__file__).resolve().parents[4])
    except (ImportError, IndexError):
        pass
    for prefix in candidates:
        d = prefix / "share" / "packml_interfaces" / "msg"
        if (d / "UnitInput.msg").exists():
            return d
    return Path(__file__).resolve().parents[2] / "msg_defs" / "msg"


@functools.cache
def typestore() -> Any:
    """A rosbags typestore: ROS 2 Kilted's standard types plus the installed packml_interfaces."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_KILTED)
    types: dict[str, Any] = {}
    for f in sorted(interface_dir().glob("*.msg")):
        types.update(
            get_types_from_msg(f.read_text(encoding="utf-8"), f"packml_interfaces/msg/{f.stem}")
        )
    store.register(types)
    return store


@functools.cache
def installed_hash(msgtype: str) -> str:
    """RIHS01 of the installed definition of ``pkg/msg/Name``: the one rosidl wrote beside the
    installed ``.msg`` file (``<Name>.json``, ``type_hashes``), else computed by :func:`typestore`
    (whose first use parses every definition: about half a second, more than reading a bag)."""
    pkg, _, name = msgtype.split("/")
    here = interface_dir()
    description = here.parents[1] / pkg / "msg" / f"{name}.json"
    if here.parent.name == "packml_interfaces" and here.parents[1].name == "share":
        try:
            with description.open(encoding="utf-8") as f:
                for entry in json.load(f).get("type_hashes", []):
                    if entry.get("type_name") == msgtype and entry.get("hash_string"):
                        return str(entry["hash_string"])
        except (OSError, ValueError, AttributeError):
            pass
    return str(typestore().hash_rihs01(msgtype))


def rosbags_qos(profile: QoSProfile) -> Any:
    """A rosbags ``Qos`` (for metadata.yaml ``offered_qos_profiles``) from an rclpy profile."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return Qos(
        history=QosHistory.KEEP_LAST
        if profile.history == HistoryPolicy.KEEP_LAST
        else QosHistory.KEEP_ALL,
        depth=profile.depth,
        reliability=QosReliability.RELIABLE
        if profile.reliability == ReliabilityPolicy.RELIABLE
        else QosReliability.BEST_EFFORT,
        durability=QosDurability.TRANSIENT_LOCAL
        if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        else QosDurability.VOLATILE,
        deadline=zero,
        lifespan=zero,
        liveliness=QosLiveliness.AUTOMATIC,
        liveliness_lease_duration=zero,
        avoid_ros_namespace_conventions=False,
    )


def split_topic(topic: str) -> tuple[str, str] | None:
    """``/<cell>/<unit>/<name>`` -> (``/<cell>/<unit>``, name) for unit topics, else None."""
    prefix, _, name = topic.rpartition("/")
    if name in UNIT_TOPICS and prefix.count("/") >= 1 and prefix != "":
        if prefix.rpartition("/")[2] == "coordinator" or prefix.endswith("/coordinator/line"):
            return None
        return prefix, name
    return None
