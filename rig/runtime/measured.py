"""A port that only reads and writes (rig.port.Port: Measurements in, Commands out) reaches the period through a
block of its own (rig/runtime/exchange.py), fed from each read as the accelerometer module and the transducer
feed theirs; the commands the period writes there go back to the port's write. The ports with an exchange
block of their own (the drivers, the simulated backend) skip all this: the period reads and writes their block.
"""
from __future__ import annotations

import array

import numpy as np

from rig.port import Commands
from rig.runtime.exchange import A_COUNTED, C_SEQ, C_VALUES, Block, Layout, put_conversion, put_sample


class MalformedMeasurement(ValueError):
    """A read gave something that is not a measurement of this port's mounts (a driver bug)."""


class MeasuredBlock:
    """A block of its own fed with rig.port.Measurements, for a port that only reads and writes (and for tests
    of the kernel): each measurement goes in as the accelerometer module's would, a latest value (new_samples
    None) or counted conversions (its older ones, then the newest), the strokes as the transducer's newest
    sample (no staleness limit of its own: the accelerometers' time stamps are its), a device fault as the
    fault of device 0, "port"."""

    def __init__(self, n: int, nf: int = 0) -> None:
        self.block = Block.local(Layout(n, nf, devices=("port",)))
        self.io = self.block.io
        self.n, self.nf = n, nf
        self._a = self.block.part("accel")
        self.counter = -1
        self.seq = -1
        self._fault = None

    def put(self, m) -> None:
        n, nf, io = self.n, self.nf, self.io
        ts = _floats(m.sample_t_ns)
        newest = _floats(list(m.accel_mps2) + list(m.floor_accel_mps2)[:nf])
        if m.new_samples is None:
            io[self._a + A_COUNTED] = 0.0
            convs = [newest]
        else:
            io[self._a + A_COUNTED] = 1.0
            k = int(m.new_samples)
            older = [_floats(o[:n + nf]) for o in m.accel_older]
            convs = (older + [newest]) if k > 0 else []
            if k <= 0 and self.counter >= 0:        # no new conversion: the newest, with the read's time stamps
                put_conversion(io, float(self.counter), ts, newest)
        for values in convs:
            if values.shape[0] != n + nf:
                raise MalformedMeasurement(f"{values.shape[0]} accelerations for {n} mounts"
                                           f"{f' and {nf} floor accelerometers' if nf else ''}")
            self.counter += 1
            put_conversion(io, float(self.counter), ts, values)
        self.seq += 1
        put_sample(io, float(self.seq), float(ts.max()) if ts.size else 0.0, _floats(m.stroke_m))
        if m.device_fault != self._fault:
            self._fault = m.device_fault
            self.block.fault(0, 1 if m.device_fault else 0, m.device_fault or "")

    def commands(self) -> tuple[float, list[float]]:
        """(sequence, the commands) last written into the block."""
        c = self.block.part("cmd")
        return float(self.io[c + C_SEQ]), self.io[c + C_VALUES:c + C_VALUES + self.n].tolist()



def _floats(values) -> np.ndarray:
    """float64 values, or TypeError for anything that is not a number (None is not NaN here)."""
    return np.frombuffer(array.array("d", values), dtype=np.float64)


class MeasuredPort:
    """The loop's side of a port that only reads and writes: `update(t)` reads it into the block, `commit(t)`
    writes the commands the period put there (a new set only: the period writes one, or none in FAULT)."""

    def __init__(self, port, n: int, nf: int) -> None:
        self.port = port
        self.feed = MeasuredBlock(n, nf)
        self.exchange = self.feed.block
        self.io = self.feed.io
        self._seen = 0.0
        self._commands = Commands([0.0] * n)          # the port must copy, not keep, the list
        self.last = None                              # the last Measurements read

    def update(self, t_ns: int) -> None:
        m = self.port.read(t_ns)
        self.last = m
        try:
            self.feed.put(m)
        except (TypeError, ValueError, AttributeError) as e:
            raise MalformedMeasurement(f"{e.__class__.__name__}: {e}") from None

    def commit(self, t_ns: int) -> None:
        seq, values = self.feed.commands()
        if seq != self._seen:
            self._seen = seq
            self._commands.valve_cmd_V[:] = values
            self.port.write(t_ns, self._commands)
