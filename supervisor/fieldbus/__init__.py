"""Brand-independent field-bus code that device kinds share: SCPI text and line transports
(:mod:`supervisor.fieldbus.scpi`, :mod:`supervisor.fieldbus.scpi_transport`) and a Modbus TCP
master (:mod:`supervisor.fieldbus.modbus`).

Below ``supervisor.devices`` so that any kind folder may import it: a second SCPI supply
uses these instead of copying them or importing another kind (kinds are independent of each
other, an import-linter contract). Nothing here knows a device brand, a register map or a
point name; those stay in the kind's own folder.
"""
