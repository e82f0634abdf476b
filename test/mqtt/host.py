"""A real broker and an independent Sparkplug B host application for the MQTT tests.

:class:`Broker`: Debian's ``mosquitto`` (installed by ``tools/setup.sh --test``) on a free
127.0.0.1 port, started and killed by the test. :class:`Host`: a subscriber that decodes every
Sparkplug payload with Eclipse Tahu's protobuf definition as ``pysparkplug`` ships it, generated
by protoc (the product encodes by hand and does not use it), and keeps the names behind the
aliases of each birth, as a Sparkplug host application does.
"""

from __future__ import annotations

import contextlib
import getpass
import json
import shutil
import socket
import ssl
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

import paho.mqtt.client as paho
from pysparkplug._protobuf import Payload  # Eclipse Tahu's sparkplug_b.proto, generated

MOSQUITTO = "/usr/sbin/mosquitto"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broker:
    """mosquitto on 127.0.0.1:``port`` (a free one by default), its log in ``directory``."""

    def __init__(
        self, directory: Path, port: int | None = None, settings: str = "allow_anonymous true\n"
    ) -> None:
        if not Path(MOSQUITTO).exists():
            raise RuntimeError(
                f"{MOSQUITTO} is missing: tools/setup.sh --test installs Debian's mosquitto"
            )
        self.port = port or free_port()
        self.directory = directory
        self.conf = directory / "mosquitto.conf"
        self.conf.write_text(
            # (user: started as root, mosquitto would switch to its own user, who cannot read
            # the test's files; started as anyone else it stays who it is)
            f"listener {self.port} 127.0.0.1\n{settings}persistence false\nlog_dest stderr\n"
            f"user {getpass.getuser()}\n"
        )
        self.proc: subprocess.Popen[bytes] | None = None
        self.start()

    def start(self) -> None:
        log = (self.directory / "mosquitto.log").open("ab")
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=log, stderr=log)
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), 0.2).close()
                return
            except OSError:
                if time.monotonic() > deadline or self.proc.poll() is not None:
                    raise RuntimeError(
                        f"mosquitto did not listen on {self.port}: "
                        + (self.directory / "mosquitto.log").read_text()[-500:]
                    ) from None
                time.sleep(0.02)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def sub(self, topic: str, count: int, timeout: float = 10.0) -> list[str]:
        """``mosquitto_sub -v`` (Debian's client): the first ``count`` messages, ``topic payload``."""
        exe = shutil.which("mosquitto_sub") or "/usr/bin/mosquitto_sub"
        out = subprocess.run(
            [
                exe,
                "-h",
                "127.0.0.1",
                "-p",
                str(self.port),
                "-t",
                topic,
                "-v",
                "-C",
                str(count),
                "-W",
                str(int(timeout)),
            ],
            capture_output=True,
            timeout=timeout + 5,
            check=False,
        )
        return out.stdout.decode(errors="replace").splitlines()


@dataclass
class Seen:
    """One message as the host application saw it."""

    topic: str
    kind: str  #: NBIRTH, DBIRTH, DDATA, DDEATH, NDEATH, ... or "" (not Sparkplug)
    device: str
    payload: Any  #: the decoded Payload (Sparkplug) or the JSON (UNS)
    metrics: dict[str, Any] = field(default_factory=dict)  #: name -> value (aliases resolved)
    raw: bytes = b""
    retain: bool = False


def metric_value(m: Any) -> Any:
    which = m.WhichOneof("value")
    if m.is_null or which is None:
        return None
    value = getattr(m, which)
    if m.datatype in (1, 2, 3):  # Int8/16/32: two's complement in a uint32 (Sparkplug 3.0)
        value = value - (1 << 32) if value >> 31 else value
    elif m.datatype == 4:
        value = value - (1 << 64) if value >> 63 else value
    return value


class Host:
    """A host application: subscribes ``spBv1.0/<group>/#`` and ``extra`` topics, decodes."""

    def __init__(
        self,
        port: int,
        group: str,
        extra: tuple[str, ...] = (),
        login: tuple[str, str] | None = None,
        ca_file: Path | None = None,
    ) -> None:
        self.group = group
        self.seen: list[Seen] = []
        self.aliases: dict[tuple[str, int], str] = {}  # (device, alias) -> name
        self.errors: list[str] = []
        self.cond = threading.Condition()
        self.client = paho.Client(client_id=f"host-{port}", clean_session=True)
        self.client.on_message = self._on_message
        if login:
            self.client.username_pw_set(*login)
        if ca_file:
            self.client.tls_set(ca_certs=str(ca_file), tls_version=ssl.PROTOCOL_TLS_CLIENT)
        subscribed = threading.Event()
        self.client.on_connect = lambda c, *_: (
            c.subscribe([(f"spBv1.0/{group}/#", 1), *((t, 1) for t in extra)]),
            subscribed.set(),
        )
        self.client.connect("127.0.0.1", port, 10)
        self.client.loop_start()
        if not subscribed.wait(10):
            raise RuntimeError("the host application did not connect")

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        parts = msg.topic.split("/")
        try:
            if parts[0] == "spBv1.0" and len(parts) >= 4 and parts[2] not in ("STATE",):
                kind, device = parts[2], parts[4] if len(parts) > 4 else ""
                payload = Payload.FromString(msg.payload)
                metrics = {}
                for m in payload.metrics:
                    if kind.endswith("BIRTH") and m.HasField("alias"):
                        self.aliases[(device, m.alias)] = m.name
                    name = m.name if m.name else self.aliases.get((device, m.alias), f"?{m.alias}")
                    metrics[name] = metric_value(m)
                seen = Seen(msg.topic, kind, device, payload, metrics, msg.payload, msg.retain)
            else:
                seen = Seen(
                    msg.topic, "", "", json.loads(msg.payload), raw=msg.payload, retain=msg.retain
                )
        except Exception as exc:  # recorded; the test fails on it
            self.errors.append(f"{msg.topic}: {exc!r}")
            return
        with self.cond:
            self.seen.append(seen)
            self.cond.notify_all()

    def wait(
        self,
        predicate: Callable[[Seen], bool],
        timeout: float = 20.0,
        what: str = "",
        after: int = 0,
    ) -> Seen:
        """The first message from index ``after`` on that satisfies ``predicate``."""
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                for s in self.seen[after:]:
                    if predicate(s):
                        return s
                left = deadline - time.monotonic()
                if left <= 0:
                    kinds = [(s.kind, s.device) for s in self.seen[-15:]]
                    raise TimeoutError(
                        f"no {what or 'such message'} within {timeout:g} s; last: {kinds}"
                    )
                self.cond.wait(left)

    def mark(self) -> int:
        with self.cond:
            return len(self.seen)

    def since(self, mark: int) -> list[Seen]:
        with self.cond:
            return list(self.seen[mark:])

    def send(
        self, topic: str, metrics: list[tuple[str, int, Any]], timestamp: int | None = None
    ) -> None:
        """A command payload: (name, datatype, value) metrics, encoded by Tahu's protobuf."""
        p = Payload()
        p.timestamp = timestamp if timestamp is not None else time.time_ns() // 1_000_000
        for name, dtype, value in metrics:
            m = p.metrics.add()
            m.name, m.datatype = name, dtype
            if dtype in (1, 2, 3, 5, 6, 7):
                m.int_value = value & 0xFFFFFFFF
            elif dtype in (4, 8, 13):
                m.long_value = value & 0xFFFFFFFFFFFFFFFF
            elif dtype == 9:
                m.float_value = value
            elif dtype == 10:
                m.double_value = value
            elif dtype == 11:
                m.boolean_value = value
            else:
                m.string_value = value
        self.publish(topic, p.SerializeToString())

    def publish(self, topic: str, raw: bytes) -> None:
        self.client.publish(topic, raw, qos=1).wait_for_publish(10)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def tls_files(folder: Path) -> tuple[Path, Path, Path]:
    """A CA and a server certificate for 127.0.0.1 signed by it (PEM): (ca, cert, key)."""
    import datetime as dt
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    now = dt.datetime.now(dt.timezone.utc)
    ca_key, key = ec.generate_private_key(ec.SECP256R1()), ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "test broker CA")])
    ca = (x509.CertificateBuilder().subject_name(ca_name).issuer_name(ca_name)
          .public_key(ca_key.public_key()).serial_number(1)
          .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=1))
          .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
          .sign(ca_key, hashes.SHA256()))  # fmt: skip
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")]))
            .issuer_name(ca_name).public_key(key.public_key()).serial_number(2)
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
            .sign(ca_key, hashes.SHA256()))  # fmt: skip
    files = folder / "ca.pem", folder / "server.pem", folder / "server.key"
    files[0].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    files[1].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    files[2].write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))  # fmt: skip
    return files


def password_file(folder: Path, users: dict[str, str]) -> Path:
    """A mosquitto password file (Debian's mosquitto_passwd)."""
    path = folder / "passwords"
    path.touch()
    for user, password in users.items():
        subprocess.run(["mosquitto_passwd", "-b", str(path), user, password], check=True,
                       capture_output=True, timeout=30)  # fmt: skip
    return path


def close_all(host: Host, procs: Any, broker: Broker) -> str:
    """The end of an MQTT test: the host, the processes (their failures returned), the broker."""
    host.close()
    failures: str = procs.close()
    broker.kill()
    return failures


class _Closes(Protocol):
    def close(self) -> str: ...


F = TypeVar("F", bound=_Closes)


@contextlib.contextmanager
def closed_cleanly(face: F) -> Iterator[F]:
    """A test's MQTT setup (its ``close()`` returns its processes' failures), closed at the end of
    the test; a process that failed fails the test."""
    try:
        yield face
    finally:
        failures = face.close()
        assert not failures, failures
