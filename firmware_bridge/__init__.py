"""Firmware bridge: the brick program, its wire protocol and the host that records field and HIL logs.

``firmware_bridge.brick`` runs on the brick (Pybricks/ev3dev MicroPython) and on CPython; the host
imports its protocol codec, so brick and host share one implementation of the wire format.
"""
