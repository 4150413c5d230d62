"""The OPC UA server of a bench (docs/design.md "Publishing"; docs/adr/0014-opcua-server.md).

``opc.tcp://<host>:4840/supervisor``: the bench's tags under Bench / Channels / Devices /
Alarms / Diagnostics (NodeIds equal to tag names), analog tags as AnalogItemType with
their units and range, quality as status codes, methods on each channel through the one
command path, events for steps, commands and alarms, users with roles and a secure
endpoint. ``supervisor.app.opcua`` wires it to a bench.
"""

from supervisor.config.users import ROLES, UserStore, add_user, remove_user
from supervisor.publish.opcua.feed import AlarmView, OpcUaFeed
from supervisor.publish.opcua.layout import Layout, namespace_uri, plan
from supervisor.publish.opcua.ports import Answer, Operate, Request
from supervisor.publish.opcua.process import OpcUaProcess
from supervisor.publish.opcua.security import ACTOR_PREFIX, OpcUaRoles
from supervisor.publish.opcua.server import OpcUaServer, OpcUaSettings

__all__ = [
    "ACTOR_PREFIX",
    "ROLES",
    "AlarmView",
    "Answer",
    "Layout",
    "OpcUaFeed",
    "OpcUaProcess",
    "OpcUaRoles",
    "OpcUaServer",
    "OpcUaSettings",
    "Operate",
    "Request",
    "UserStore",
    "add_user",
    "namespace_uri",
    "plan",
    "remove_user",
]
