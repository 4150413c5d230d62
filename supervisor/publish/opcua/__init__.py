"""The OPC UA server of a bench (docs/design.md "Publishing"; docs/adr/0014-opcua-server.md).

``opc.tcp://<host>:4840/supervisor``: the bench's tags under Bench / Channels / Devices /
Alarms / Diagnostics (NodeIds equal to tag names), analog tags as AnalogItemType with
their units and range, quality as status codes, methods on each channel through the one
command path, events for steps, commands and alarms, users with roles and a secure
endpoint. ``supervisor.app.opcua`` wires it to a bench.
"""

from typing import TYPE_CHECKING, Any

from supervisor.config.users import ROLES, UserStore, add_user, remove_user
from supervisor.publish.opcua.feed import AlarmView, OpcUaFeed
from supervisor.publish.opcua.layout import Layout, namespace_uri, plan
from supervisor.publish.opcua.ports import Answer, Operate, Request
from supervisor.publish.opcua.process import OpcUaProcess
from supervisor.publish.opcua.settings import OpcUaSettings

if TYPE_CHECKING:
    from supervisor.publish.opcua.security import ACTOR_PREFIX, OpcUaRoles
    from supervisor.publish.opcua.server import OpcUaServer

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

_LAZY = {
    "ACTOR_PREFIX": "supervisor.publish.opcua.security",
    "OpcUaRoles": "supervisor.publish.opcua.security",
    "OpcUaServer": "supervisor.publish.opcua.server",
}
"""Names whose modules import asyncua: loaded when first asked for (PEP 562), so that a
command that only reads the settings or the users file imports no OPC UA stack."""


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
