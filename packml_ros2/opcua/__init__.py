"""A PackML cell as an OPC UA server following OPC 30050 "OPC UA for PackML" (asyncua).

``packml opcua <cell.yaml>`` (or ``packml launch <cell.yaml> --opcua``) serves every unit of the
cell as a ``PackMLBaseObjectType`` object under ``Objects/PackMLObjects``: Status, Admin, the
Base/Machine/Execute state machines with their methods, SetUnitMode and SetMachSpeed. Values
follow the units' ROS topics; methods call the units' services. See :mod:`.model` for the node
structure, :mod:`.security` for access control, :mod:`.config` for the ``opcua:`` block.
"""

from .config import OpcUaConfig, hash_password, parse_opcua

__all__ = ["OpcUaConfig", "hash_password", "parse_opcua"]
