"""Emulated devices behind the real drivers (HIL): CANopen valve nodes, Modbus TCP I/O, serial amplifier.

Imported only by the `hil` backend; nothing here is loaded by a simulated run.
"""
