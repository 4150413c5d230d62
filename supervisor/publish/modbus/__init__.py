"""The tag database as a Modbus TCP server (issue 36): panel HMIs and SCADA that speak
only Modbus read the bench and command it through the one command path.

``regmap``: the register map, a contract (stable addresses, documented as CSV by
``supervisor modbus map``); ``server``: the server (pymodbus), fed by the scan's copy of
its changes, never the scan's time.
"""

from supervisor.publish.modbus.regmap import Kind, Point, RegisterMap, Table

__all__ = ["Kind", "Point", "RegisterMap", "Table"]
