"""Devices: one package per kind (codec, config and point catalog, driver, simulator)."""
