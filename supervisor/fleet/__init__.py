"""The fleet overview: a Sparkplug B host application over a lab's benches (issue 35,
docs/fleet.md).

``Fleet`` keeps each edge node's births, data and death (``state``); ``FleetHost`` is its
MQTT subscription and rebirth requests (``host``); ``FleetServer`` serves ``GET /api/fleet``
and the fleet page behind the HMI's login (``server``). ``supervisor fleet`` (cli) runs them.
"""

from supervisor.fleet.host import FleetHost, rebirth_request
from supervisor.fleet.server import FleetServer
from supervisor.fleet.state import Device, Fleet, Node
from supervisor.fleet.view import fleet_json

__all__ = ["Device", "Fleet", "FleetHost", "FleetServer", "Node", "fleet_json", "rebirth_request"]
