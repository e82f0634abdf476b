"""A PackML cell as an OPC UA server following OPC 30050 "OPC UA for PackML" v1.01 (asyncua).

``packml opcua <cell.yaml>`` (or ``packml launch <cell.yaml> --opcua``) loads the official NodeSet
(:mod:`.nodeset`) and serves every unit of the cell as a ``PackMLBaseObjectType`` object under
``Objects/PackMLObjects``, instantiated from its types (:mod:`.model`): Status, Admin, the
Base/Machine/Execute state machines with their methods and available states and transitions
(:mod:`.available`), SetUnitMode, SetMachSpeed, SetParameter, SetProduct. Values follow the units'
ROS topics (:mod:`.mapping`); methods call the units' services (:mod:`.bridge`); a unit that is
gone (:mod:`packml_ros2.presence`) looks gone. See :mod:`.security` for access control,
:mod:`.config` for the ``opcua:`` block.
"""

from .config import OpcUaConfig, hash_password, parse_opcua

__all__ = ["OpcUaConfig", "hash_password", "parse_opcua"]
