"""Watch network interfaces for RTPS (DDS) packets with a raw socket (Linux, needs CAP_NET_RAW)."""

from __future__ import annotations

import socket
import struct
import threading
from pathlib import Path

ETH_P_ALL = 0x0003


def interfaces(include_loopback: bool = False) -> list[str]:
    names = sorted(p.name for p in Path("/sys/class/net").iterdir())
    return [n for n in names if include_loopback or n != "lo"]


class RtpsWatch:
    """Counts frames carrying an RTPS message (UDP payload starting with b"RTPS")."""

    def __init__(self, names: list[str]) -> None:
        self.names = names
        self.packets: list[str] = []
        self.frames = 0
        self._stop = threading.Event()
        self._sockets: list[socket.socket] = []
        for name in names:
            s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.ntohs(ETH_P_ALL))
            s.bind((name, 0))
            s.settimeout(0.2)
            self._sockets.append(s)
        self._threads = [
            threading.Thread(target=self._run, args=(s, n), daemon=True)
            for s, n in zip(self._sockets, names, strict=True)
        ]

    @classmethod
    def on_external_interfaces(cls) -> RtpsWatch | None:
        try:
            return cls(interfaces(include_loopback=False))
        except PermissionError:
            return None

    @classmethod
    def on(cls, names: list[str]) -> RtpsWatch:
        return cls(names)

    def start(self) -> RtpsWatch:
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(2)
        for s in self._sockets:
            s.close()

    def _run(self, s: socket.socket, name: str) -> None:
        while not self._stop.is_set():
            try:
                frame = s.recv(65535)
            except TimeoutError:
                continue
            except OSError:
                return
            self.frames += 1
            found = _rtps(frame, loopback=name == "lo")
            if found:
                self.packets.append(f"{name}: {found}")


def _rtps(frame: bytes, loopback: bool) -> str | None:
    """'src -> dst:port' when the frame is IPv4/UDP with an RTPS payload."""
    offset = 14  # Ethernet header (loopback frames carry a zero Ethernet header too)
    if len(frame) < offset + 28:
        return None
    ethertype = struct.unpack("!H", frame[12:14])[0]
    if ethertype == 0x8100:  # VLAN tag
        offset += 4
        ethertype = struct.unpack("!H", frame[16:18])[0]
    if ethertype != 0x0800:
        return None
    ip = frame[offset:]
    ihl = (ip[0] & 0x0F) * 4
    if ip[9] != 17:  # UDP
        return None
    udp = ip[ihl:]
    if udp[8:12] != b"RTPS":
        return None
    src = socket.inet_ntoa(ip[12:16])
    dst = socket.inet_ntoa(ip[16:20])
    dport = struct.unpack("!H", udp[2:4])[0]
    return f"{src} -> {dst}:{dport}"
