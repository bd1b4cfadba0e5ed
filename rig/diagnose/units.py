"""The measured output's amounts in words: a position in m reads in nm, um or mm; any other output (a plant
file's [signals] output: a speed, a voltage, a pressure, a sensor's own units "1") in its own SI unit."""
from __future__ import annotations


def amount(x: float, unit: str = "m", spec: str = ".3g") -> str:
    """x in unit, readable: a length in nm, um or mm; "1" (a sensor's own units) without a unit."""
    if unit == "m":
        for name, scale in (("nm", 1e9), ("um", 1e6)):
            if abs(x) * scale < 1000.0:
                return f"{x * scale:{spec}} {name}"
        return f"{x * 1e3:{spec}} mm"
    return f"{x:{spec}}" + ("" if unit == "1" else f" {unit}")


def per_second(x: float, unit: str = "m", spec: str = ".3g") -> str:
    """A drift: x unit/s."""
    return amount(x, unit, spec) + ("/s" if unit != "1" else " per s")


def name(unit: str) -> str:
    """The unit as a column heading's words."""
    return "sensor units" if unit == "1" else unit
