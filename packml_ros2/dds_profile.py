"""The network interfaces a cell's DDS traffic may use (the cell file's ``dds.interfaces``).

Fast DDS listens and sends on every interface of the host unless its transports are restricted.
A cell that names its interfaces::

    dds:
      interfaces: [eth1, 192.168.10.5]   # interface names or IPv4 addresses of this host

gets a Fast DDS profile (:func:`profile_xml`) whose UDPv4 transport is limited to those of them
this host has, plus 127.0.0.1 and shared memory for the host's own processes; ``packml launch``
writes it (:func:`apply`) and points ``FASTDDS_DEFAULT_PROFILES_FILE`` at it for every node it
starts, in its process and in the processes it starts. A host that has none of the named
interfaces is refused before anything starts (:func:`missing`): DDS would reach nobody. Without
the key the environment decides (``packml_ros2.run.default_environment``: loopback only while
``ROS_AUTOMATIC_DISCOVERY_RANGE`` is LOCALHOST).
"""

from __future__ import annotations

import errno
import ipaddress
import os
import socket
import tempfile
from collections.abc import Sequence
from pathlib import Path
from xml.sax.saxutils import escape

from .core.config import CellConfig

PROFILE_NAME = "packml_interfaces"


def on_this_host(interface: str) -> bool:
    """Whether ``interface`` (a name or an IPv4 address) is one of this host's."""
    try:
        ipaddress.IPv4Address(interface)
    except ValueError:
        return interface in {name for _, name in socket.if_nameindex()}
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind((interface, 0))  # only a local address can be bound
        except OSError as exc:
            if exc.errno == errno.EADDRNOTAVAIL:
                return False
            raise
    return True


def missing(cell: CellConfig) -> list[tuple[str, str]]:
    """A problem (key path, text) when the cell names interfaces and this host has none of them."""
    if not cell.dds_interfaces or any(on_this_host(i) for i in cell.dds_interfaces):
        return []
    names = ", ".join(name for _, name in socket.if_nameindex())
    return [
        (
            "dds.interfaces",
            f"this host has none of {', '.join(cell.dds_interfaces)} "
            f"(its interfaces: {names}): DDS would reach nobody",
        )
    ]


def profile_xml(interfaces: Sequence[str]) -> str:
    """A Fast DDS participant profile (the default one): UDPv4 on ``interfaces`` and 127.0.0.1,
    shared memory, and the quick discovery of config/fastdds_localhost.xml."""
    allowed = ["<address>127.0.0.1</address>"]
    for interface in interfaces:
        try:
            allowed.append(f"<address>{ipaddress.IPv4Address(interface)}</address>")
        except ValueError:
            allowed.append(f"<interface>{escape(interface)}</interface>")
    return f"""<?xml version="1.0" encoding="UTF-8" ?>
<!-- written by packml launch from the cell file's dds.interfaces -->
<dds xmlns="http://www.eprosima.com">
  <profiles>
    <transport_descriptors>
      <transport_descriptor>
        <transport_id>packml_udp</transport_id>
        <type>UDPv4</type>
        <interfaceWhiteList>{"".join(allowed)}</interfaceWhiteList>
      </transport_descriptor>
      <transport_descriptor>
        <transport_id>packml_shm</transport_id>
        <type>SHM</type>
      </transport_descriptor>
    </transport_descriptors>
    <participant profile_name="{PROFILE_NAME}" is_default_profile="true">
      <rtps>
        <builtin>
          <discovery_config>
            <initialAnnouncements>
              <count>10</count>
              <period><sec>0</sec><nanosec>50000000</nanosec></period>
            </initialAnnouncements>
            <leaseAnnouncement><sec>0</sec><nanosec>500000000</nanosec></leaseAnnouncement>
            <leaseDuration><sec>5</sec><nanosec>0</nanosec></leaseDuration>
          </discovery_config>
        </builtin>
        <userTransports>
          <transport_id>packml_udp</transport_id>
          <transport_id>packml_shm</transport_id>
        </userTransports>
        <useBuiltinTransports>false</useBuiltinTransports>
      </rtps>
    </participant>
  </profiles>
</dds>
"""


def profile_path(cell: CellConfig) -> Path:
    """Where the profile of ``cell`` is written: beside its units' stores, else a private
    temporary directory."""
    for unit in cell.units.values():
        if unit.persistence_path:
            return Path(unit.persistence_path).expanduser().parent / "fastdds_interfaces.xml"
    return Path(tempfile.gettempdir()) / f"packml_ros2-{os.getuid()}" / f"{cell.cell}.xml"


def apply(cell: CellConfig) -> Path | None:
    """Write the profile of the cell's ``dds.interfaces`` (those this host has) and select it for
    this process and the ones it starts; None (nothing changed) when the cell names none."""
    if not cell.dds_interfaces:
        return None
    here = [i for i in cell.dds_interfaces if on_this_host(i)]
    path = profile_path(cell)
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    temporary = path.with_name(f".{path.name}.{os.getpid()}")
    temporary.write_text(profile_xml(here), encoding="utf-8")
    temporary.replace(path)  # (another launcher of the cell reads a whole file)
    os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] = str(path)
    return path
