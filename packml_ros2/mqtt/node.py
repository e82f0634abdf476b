"""``packml mqtt``: the cell's :class:`~.edge.Edge` on a real broker (paho-mqtt) and real units
(the OPC UA server's :class:`~packml_ros2.opcua.bridge.RosSide`: a node of its own in a thread).

Threads: paho's network thread (connects, reconnects with back-off 1..30 s, delivers NCMD and
DCMD), the ROS thread (status, admin, presence), and the asyncio loop of the main thread, where
the service calls of commands are awaited. The edge's state is changed under one lock, and each
message is published in the order the edge made it. The will (NDEATH) carries the bdSeq of its
connection: a new one is registered before each reconnection. While the broker is away nothing
is buffered but paho's in-flight messages (``buffer``): on the next connection, NBIRTH and the
DBIRTHs carry every current value.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import ssl
import threading
import time
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as paho

from ..client import Unavailable
from ..core.config import CellConfig
from ..core.rules import source_of
from ..opcua.bridge import FOLLOWED, RosSide
from ..presence import Seen
from .config import MqttConfig
from .edge import INVALID_ARGUMENT, UNIT_UNAVAILABLE, Edge, Message, Refused, Request

log = logging.getLogger("packml_mqtt")
MAX_LOGGED_REFUSALS = 100  #: refusals logged one by one; after that, one line per 1000


def _result_names() -> dict[int, str]:
    from packml_interfaces.msg import Result

    return {v: k for k, v in vars(Result).items() if k.isupper() and isinstance(v, int)}


def now_ms() -> int:
    return time.time_ns() // 1_000_000


class _RosSide(RosSide):
    """The OPC UA server's ROS side, handing status and admin messages over in the ROS thread
    itself (the edge is changed under its lock): one thread hop less on the way to a DDATA."""

    def _changed(self, path: str, topic: str, msg: Any) -> None:
        if topic in FOLLOWED:
            self._on_message(path.rsplit("/", 1)[-1], topic, msg)


class MqttFace:
    """One edge node: ``start()``, then ``run()`` until a signal or :meth:`stop`."""

    def __init__(
        self, cell: CellConfig, config: MqttConfig, ready: Callable[[str], None] = print
    ) -> None:
        self.cell = cell
        self.config = config
        self.ready = ready
        self.source = source_of("mqtt", config.client)
        self.loop = asyncio.new_event_loop()
        self.edge = Edge(config, now_ms)
        self.lock = threading.RLock()
        self.refusals = 0
        self.dropped = 0
        self.names = _result_names()
        self._ready_said = False
        self.present: dict[str, bool] = dict.fromkeys(config.units, False)
        self.ros = RosSide(
            cell.cell,
            config.units,
            self.loop,
            self._on_unit,
            self._on_presence,
            cell.coordinator.unit_lease,
        )
        self.client = paho.Client(
            client_id=config.client, clean_session=True, protocol=paho.MQTTv311
        )
        if config.username:
            self.client.username_pw_set(config.username, config.password or None)
        if config.tls is not None:
            t = config.tls
            self.client.tls_set(
                ca_certs=str(t.ca_file) if t.ca_file else None,
                certfile=str(t.cert_file) if t.cert_file else None,
                keyfile=str(t.key_file) if t.key_file else None,
                tls_version=ssl.PROTOCOL_TLS_CLIENT,
            )
        self.client.reconnect_delay_set(1, 30)
        self.client.max_queued_messages_set(config.buffer)
        self.client.on_connect = self._on_connect
        self.client.on_disconnect = self._on_disconnect
        self.client.on_message = self._on_message
        self._will(self.edge.connecting())

    # -- MQTT side (paho's thread) ------------------------------------------------------------------
    def _will(self, death: Message) -> None:
        self.client.will_set(death.topic, death.payload, qos=death.qos, retain=False)

    def _publish(self, messages: list[Message]) -> None:
        for m in messages:
            info = self.client.publish(m.topic, m.payload, qos=m.qos, retain=m.retain)
            if info.rc != paho.MQTT_ERR_SUCCESS and self.edge.connected:
                self.dropped += 1  # the in-flight buffer is full (or the connection just went)
                if self.dropped <= MAX_LOGGED_REFUSALS or self.dropped % 1000 == 0:
                    log.warning(
                        "dropped a message to %s: %s [%d dropped]",
                        m.topic[:120],
                        paho.error_string(info.rc),
                        self.dropped,
                    )

    def _on_connect(self, client: Any, userdata: Any, flags: Any, rc: int) -> None:
        if rc != 0:
            log.warning(
                "the broker %s:%d refused the connection: %s",
                self.config.host,
                self.config.port,
                paho.connack_string(rc),
            )
            return
        client.subscribe([(self.config.topic("NCMD"), 1), (self.config.topic("DCMD") + "/+", 1)])
        with self.lock:
            out = self.edge.connected_births()
            for unit in self.config.units:
                out += self.edge.uns(unit, self.present[unit])
            self._publish(out)
        log.info(
            "connected to %s:%d (bdSeq %d)", self.config.host, self.config.port, self.edge.bd_seq
        )
        if not self._ready_said:
            self._ready_said = True
            self.ready(
                f"MQTT Sparkplug B edge node {self.config.group_id}/{self.config.edge} on "
                f"{self.config.host}:{self.config.port} (units: {', '.join(self.config.units)})"
            )

    def _on_disconnect(self, client: Any, userdata: Any, rc: int) -> None:
        with self.lock:
            self.edge.connected = False
            self._will(self.edge.connecting())  # the next connection's bdSeq and will
        if rc != 0:
            log.warning(
                "lost the broker %s:%d (%s); reconnecting",
                self.config.host,
                self.config.port,
                paho.error_string(rc),
            )

    def _on_message(self, client: Any, userdata: Any, msg: Any) -> None:
        try:
            parts = msg.topic.split("/")
            if len(parts) == 4 and parts[2] == "NCMD":
                with self.lock:
                    self._publish(self.edge.node_command(msg.payload))
            elif len(parts) == 5 and parts[2] == "DCMD":
                self._dcmd(parts[4], msg.payload)
        except Refused as exc:
            self._refused(msg.topic, exc.reason, str(exc))

    def _refused(self, topic: str, reason: str, text: str) -> None:
        self.refusals += 1
        if self.refusals <= MAX_LOGGED_REFUSALS or self.refusals % 1000 == 0:
            log.warning(
                "refused a command on %s: %s (%s) [%d refused]",
                topic[:120],
                text,
                reason,
                self.refusals,
            )

    def _dcmd(self, unit: str, raw: bytes) -> None:
        with self.lock:
            try:
                request = self.edge.command(unit, raw)
            except Refused as exc:
                if unit in self.edge.devices:
                    self._publish(
                        self.edge.answer(
                            unit,
                            exc.request_id,
                            exc.shown,
                            False,
                            INVALID_ARGUMENT,
                            exc.reason,
                            str(exc),
                        )
                    )
                raise
        asyncio.run_coroutine_threadsafe(self._call(request), self.loop)

    # -- ROS side (the loop) ------------------------------------------------------------------------
    async def _call(self, r: Request) -> None:
        try:
            answer = await self.ros.call(
                r.unit, r.service, self.config.call_timeout, **r.fields, source=self.source
            )
            accepted, result, message = (
                bool(answer.accepted),
                int(answer.result),
                str(answer.message),
            )
        except Unavailable as exc:
            accepted, result, message = False, UNIT_UNAVAILABLE, str(exc)
        reason = self.names.get(result, str(result))
        with self.lock:
            self._publish(
                self.edge.answer(r.unit, r.request_id, r.shown, accepted, result, reason, message)
            )

    def _on_unit(self, unit: str, topic: str, msg: Any) -> None:
        with self.lock:
            out = self.edge.update(unit, topic, msg)
            if out and self.present[unit]:
                out += self.edge.uns(unit, True)
            self._publish(out)

    def _on_presence(self, unit: str, seen: Seen) -> None:
        with self.lock:
            self.present[unit] = bool(seen.present)
            out = self.edge.presence(unit, bool(seen.present))
            if seen.present is not None:
                out += self.edge.uns(unit, bool(seen.present))
            self._publish(out)

    # -- running ------------------------------------------------------------------------------------
    def run(self) -> int:
        """Connect (retrying while the broker is away), serve until SIGINT or SIGTERM."""
        asyncio.set_event_loop(self.loop)
        for sig in (signal.SIGINT, signal.SIGTERM):
            self.loop.add_signal_handler(sig, self.loop.stop)
        self.ros.start()
        self.client.connect_async(self.config.host, self.config.port, self.config.keepalive)
        self.client.loop_start()
        try:
            self.loop.run_forever()
        finally:
            self.close()
        return 0

    def close(self) -> None:
        """A clean goodbye: NDEATH (a clean disconnect sends no will), then disconnect."""
        with self.lock:
            connected = self.edge.connected
            death = self.edge.death()
            self.edge.connected = False
        if connected:
            info = self.client.publish(death.topic, death.payload, qos=1)
            with contextlib.suppress(Exception):
                info.wait_for_publish(2.0)
        self.client.disconnect()
        self.client.loop_stop()
        self.ros.stop()
        with contextlib.suppress(Exception):
            self.loop.close()
