"""MQTT Sparkplug B and the Unified Namespace: the cell as a Sparkplug B edge node, each unit a
device (:mod:`.edge`, pure), on a broker (:mod:`.node`), configured by the cell file's ``mqtt:``
block (:mod:`.config`); payloads encoded and decoded by :mod:`.sparkplug`."""

from .config import MqttConfig, parse_mqtt

__all__ = ["MqttConfig", "parse_mqtt"]
