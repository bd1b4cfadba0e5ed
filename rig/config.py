"""Typed configuration, loaded from one TOML file; defaults are the paper's Table 1 identified values.

Every section is a frozen dataclass. Field metadata gives the unit and the physical range, so a wrong value
ends in one line naming the file and the key (`ConfigError`). Later issues add sections here.
The ranges are physical, not tuned: wide enough for any rig of this kind (a 10 g slider to a 100 t ram), narrow
enough to catch a slipped exponent. Every frequency in Hz of the controller, vibration and stand sections is
below the Nyquist frequency of the loop rate it runs at (`check_nyquist`).
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path

from rig.errors import ConfigError
from rig.textfile import read_text

MOUNTS = ("front_left", "front_right", "rear_left", "rear_right")
MAX_MOUNTS = 8                 # the period kernel's limit (rig/runtime/kernel.py)
PLANTS = ("machine", "stand")


def mount_names(n: int) -> tuple[str, ...]:
    """Names of n mounts: MOUNTS order, `mount<i>` beyond the four."""
    return MOUNTS[:n] if n <= len(MOUNTS) else tuple(f"mount{i}" for i in range(n))


MIN_HZ = 1e-3                  # the lowest frequency any key may name: a period of about 17 minutes


def _f(default, unit="", *, gt=None, ge=None, le=None, lt=None, choices=None, n=None, nyquist=True):
    """A config field with its unit and physical range (for a list: of each value; n = its length).
    nyquist: a frequency (unit Hz) is also below the Nyquist frequency of the loop (check_nyquist).
    A frequency stated as > 0 is >= MIN_HZ: a corner at 1e-300 Hz overflows the discretised filters."""
    if unit == "Hz" and gt == 0 and ge is None:
        gt, ge = None, MIN_HZ
    return field(default=default, metadata={"unit": unit, "gt": gt, "ge": ge, "le": le, "lt": lt,
                                            "choices": choices, "n": n, "nyquist": nyquist})


SEED_MAX = 2 ** 32 - 1                      # numpy seeds are unsigned
STAND_BASE_MASS_KG = 280.0                  # the test stand's mode mass m_b = 5 M: the absolute piston reading
                                            # fits p03_base to its noise floor with it (docs/MODEL.md)


@dataclass(frozen=True)
class LayoutConfig:
    """What the mounts stand on. "machine": the flexible machine of [machine] on its four mounts (Eq. 15,
    Table 2). "stand": each mount an actuator alone on its test stand with its load; the prototype of the
    paper's Fig. 2 is one such mount (drivers/devicemaps/prototype.toml). Any count from 1 to MAX_MOUNTS."""
    plant: str = _f("machine", "", choices=PLANTS)
    mounts: tuple[str, ...] = _f((), "")        # mount names (default: MOUNTS for the machine, stand for a stand)
    load_kg: float = _f(0.0, "kg", ge=0, le=1e6)   # stand: mass carried on the piston beyond actuator.M


@dataclass(frozen=True)
class ActuatorConfig:
    """Table 1, actuator data (CAD estimates; C and K_L identified)."""
    M: float = _f(56.0, "kg", ge=0.01, le=1e5)            # moving mass: a 10 g slider to a 100 t ram
    A_p: float = _f(3.10e-2, "m^2", ge=1e-6, le=1.0)      # active piston area: bore ~1 mm to ~1.1 m
    C: float = _f(1951.0, "N s/m", ge=0, le=1e8)          # viscous coefficient (identified)
    V_t: float = _f(5.39e-4, "m^3", ge=1e-8, le=1.0)      # total chamber volume: 0.01 ml to 1000 l
    K_L: float = _f(6.8e8, "N/m", ge=1.0, le=1e11)        # static (membrane spring) stiffness; steel ~1e10
    stroke_m: float = _f(1.0e-3, "m", ge=1e-6, le=1.0)    # usable stroke either side of mid-stroke


@dataclass(frozen=True)
class ValveConfig:
    """Table 1, proportional valve (D3FP) data; identified values."""
    K_v: float = _f(2.0, "mA/V", ge=1e-3, le=1e3)          # driver gain, voltage -> current
    K_Q: float = _f(1.94e-6, "m^3/s/mA", ge=1e-12, le=1e-2)  # flow gain (1e-2: 12000 l/min at 20 mA)
    K_C: float = _f(6.6e-11, "m^3/s/Pa", ge=1e-18, le=1e-6)  # flow-pressure coefficient
    w_nv: float = _f(524.0, "rad/s", ge=6.0, le=1.3e5)      # apparent natural frequency: ~1 Hz to ~20 kHz
    zeta: float = _f(0.65, "", gt=0, le=10)                # apparent damping ratio (overdamped fits < 10)
    max_V: float = _f(10.0, "V", gt=0, le=50)              # command range of the valve amplifier (+-)


@dataclass(frozen=True)
class FluidConfig:
    beta: float = _f(1.4e9, "Pa", ge=1e7, le=1e10)   # effective bulk modulus: aerated oil to water/glycol


@dataclass(frozen=True)
class MachineConfig:
    """The flexible machine on the four mounts (Eq. 15, Table 2)."""
    mass_kg: float = _f(16000.0, "kg", ge=1.0, le=1e6)   # up to 1000 t
    modal_model: str = _f("", "path")           # empty: the embedded Table 2 model (sim_backend/data)
    modal_damping: float = _f(0.03, "", gt=0, lt=1)


@dataclass(frozen=True)
class LoopConfig:
    rate_hz: float = _f(5000.0, "Hz", ge=10, le=100000)
    # catch_up by default: on a non-real-time host a skipped period is a delay the isolation loop may not survive
    overrun_policy: str = _f("catch_up", "", choices=("skip", "catch_up"))
    realtime: bool = _f(True, "")               # try SCHED_FIFO, affinity, mlockall where allowed
    rt_priority: int = _f(80, "", ge=1, le=99)  # SCHED_FIFO priority of the loop thread
    cpu: int = _f(-1, "", ge=-1, le=4095)       # CPU the loop thread is pinned to (-1 = the last one)
    # real clock: sleep until spin_us before each deadline, then spin (hybrid wait; compare with
    # `rig bench loop --spin-us US`)
    spin_us: float = _f(60.0, "us", ge=0, le=1000)
    # CPU wake-up latency requested from the OS power management while the loop runs (PM QoS,
    # /dev/cpu_dma_latency, as cyclictest does); -1 leaves it alone. 0 keeps idle CPUs out of halt, which
    # shortens the wake-up tail of a sleeping loop (README: loop timing)
    cpu_latency_us: int = _f(0, "us", ge=-1, le=1000000)
    # idle CPUs kept polling while the loop runs (one SCHED_IDLE poller per CPU), where the PM QoS request above
    # cannot keep them out of halt: auto = when no cpuidle driver honours it (many virtual machines);
    # docs/REALTIME.md
    idle_poll: str = _f("auto", "", choices=("auto", "on", "off"))


@dataclass(frozen=True)
class SafetyConfig:
    """Plausibility checks and limits applied every period (rig/runtime/safety.py)."""
    valve_limit_V: float = _f(10.0, "V", gt=0, le=50)   # command clamp, <= valve.max_V
    slew_V_per_s: float = _f(1.0e4, "V/s", gt=0, le=1e8)        # command slew limit
    accel_range_mps2: float = _f(50.0, "m/s^2", gt=0, le=1e4)   # accelerometer range (<= ~1000 g)
    stroke_range_m: float = _f(2.0e-3, "m", gt=0, le=1.0)       # transducer range; beyond = implausible
    stroke_limit_m: float = _f(0.9e-3, "m", gt=0, le=1.0)       # stroke limit (fault), <= actuator.stroke_m
    stale_s: float = _f(0.002, "s", gt=0, le=10)                # a sample older than this is stale
    stuck_samples: int = _f(250, "", gt=1, le=10000000)         # same value over this many new samples = stuck
    watchdog_s: float = _f(0.05, "s", gt=0, le=10)              # loop silent for longer = fault, valve to null
    saturation_s: float = _f(1.0, "s", gt=0, le=3600)           # command at the clamp this long = not in control
    # the loop's timing (rig/runtime/scheduler.py): how far behind real time it may run, the share of deadlines it may
    # miss over a window, and the share of its period one period's work may take (measured over the first
    # periods at start-up: above it the rate is refused)
    lag_limit_s: float = _f(0.05, "s", gt=0, le=10)      # period deadline this far behind real time = fault
    missed_limit: float = _f(0.5, "", gt=0, le=1)        # missed deadlines over missed_window_s = fault
    missed_window_s: float = _f(1.0, "s", gt=0, le=60)
    period_budget: float = _f(0.5, "", gt=0, le=1)       # a period's work (p50) / the period, at start-up
    # limit cycle in the valve command (rig/runtime/safety.py check_oscillation): the command swinging between
    # +-oscillation_level * valve_limit_V at oscillation_hz or faster, over oscillation_window_s
    oscillation_level: float = _f(0.5, "", gt=0, le=1)
    oscillation_hz: float = _f(30.0, "Hz", gt=0)
    oscillation_window_s: float = _f(0.1, "s", gt=0, le=1)


@dataclass(frozen=True)
class RecordingConfig:
    """The HDF5 recorder (rig/runtime/recorder.py)."""
    flush_s: float = _f(0.05, "s", gt=0, le=0.1)        # kill -9 loses at most this much
    ring_s: float = _f(2.0, "s", gt=0, le=60)           # ring capacity; the loop never blocks on it
    chunk_rows: int = _f(1024, "", gt=0, le=1000000)    # HDF5 chunk length, at most flush_s / 2 of rows
    # gzip: shuffle + deflate level 1, about a quarter smaller for 2.5 x the writer's CPU (`rig bench recorder`);
    # none: raw, for a loop that shares few CPUs with its devices (drivers/devicemaps/hil_2khz.toml)
    compression: str = _f("gzip", "", choices=("gzip", "none"))


@dataclass(frozen=True)
class BackendConfig:
    name: str = _f("sim", "", choices=("sim", "hil", "hardware"))


@dataclass(frozen=True)
class VibrationConfig:
    """Broadband floor vibration for demos and HIL (paper: 1-50 um in 1-50 Hz). velocity_flat: displacement
    falling as 1/f across the band (valve authority: 10 V moves the piston at most ~1.25 mm/s)."""
    band_lo_hz: float = _f(1.0, "Hz", gt=0)
    band_hi_hz: float = _f(50.0, "Hz", gt=0)
    rms_m: float = _f(3e-6, "m", ge=0, le=1e-2)           # 10 mm rms is an earthquake, not a shop floor
    spectrum: str = _f("velocity_flat", "", choices=("velocity_flat", "displacement_flat"))
    seed: int = _f(1, "", ge=0, le=SEED_MAX)
    # a floor that rocks as well as heaves (simulated rig): a component of its own, of this rms at the mounts,
    # the front mounts against the rear ("pitch") or the left against the right ("roll"), same band and spectrum
    rocking_rms_m: float = _f(0.0, "m", ge=0, le=1e-2)
    rocking_axis: str = _f("pitch", "", choices=("pitch", "roll"))


@dataclass(frozen=True)
class DriversConfig:
    """Real devices behind the `hardware` backend (drivers/devicemaps/*.md document the maps)."""
    can_interface: str = _f("socketcan", "")             # python-can interface of the valve bus
    can_channel: str = _f("can0", "")
    can_bitrate: int = _f(1000000, "bit/s", ge=10000, le=1000000)   # classic CAN
    valve_node_id_base: int = _f(1, "", ge=1, le=124)    # node id = base + mount index (MOUNTS order)
    modbus_host: str = _f("192.168.1.10", "")            # ADAM-6024-style analog I/O module
    modbus_port: int = _f(502, "", ge=1, le=65535)
    modbus_unit: int = _f(1, "", ge=0, le=247)
    modbus_timeout_s: float = _f(0.02, "s", gt=0, le=10)   # one request; the poller thread owns it
    # module host watchdog (0 = off): AO to safe values; 40021 holds tenths of a second in 16 bits
    modbus_watchdog_s: float = _f(0.5, "s", ge=0, le=6553.5)
    accel_V_per_mps2: float = _f(2.0, "V/(m/s^2)", ge=1e-4, le=100)  # sensor + conditioner: 1 mV/g to 1 kV/g
    # the module converts once per SYNC into a FIFO of its last 64 conversions (40025-40344, as the emulated
    # module does): every conversion then reaches the controllers once, in order (drivers/port.py)
    accel_sync_fifo: bool = _f(False, "")
    serial_port: str = _f("/dev/ttyUSB0", "")            # displacement-transducer amplifier
    # the calibration `rig commission` wrote (commissioning.toml: per channel its mount, sign, scale, offset),
    # applied in the drivers' conversion (drivers/conversion.py calibrated); a relative path is beside the config
    calibration: str = _f("", "")
    serial_baud: int = _f(921600, "bit/s", ge=300, le=12000000)
    stale_s: float = _f(0.02, "s", gt=0, le=10)          # a device silent for longer ends in FAULT
    serial_stale_s: float = _f(0.1, "s", gt=0, le=10)    # the same for the displacement amplifier (centring)
    thread_priority: int = _f(55, "", ge=0, le=99)       # SCHED_FIFO of the drivers' I/O processes (0 = normal)
    # Each device's rate and latency (drivers/README.md shows the timing; `rig hil --bench` measures them):
    # the valves: SYNC at the loop's rate, sync_offset_s after the period starts (after the loop wrote its
    # commands), waiting for a late loop up to sync_wait_s after the period's start
    sync_offset_s: float = _f(0.0001, "s", ge=0, le=0.1)
    sync_wait_s: float = _f(0.00025, "s", ge=0, le=0.1)
    # the accelerometer module: converts on each SYNC; its FIFO fetched every accel_fetch_every SYNCs (the
    # conversions then reach the loop in blocks of that many), accel_fetch_delay_s after the SYNC (the module's
    # conversion time)
    accel_fetch_every: int = _f(1, "", ge=1, le=32)
    accel_fetch_delay_s: float = _f(0.0001, "s", ge=0, le=0.1)
    # periods from a conversion's SYNC to the SYNC whose commands it changes: 1 when the conversion reaches the
    # loop within the period (SYNC early in it), 2 when sync_offset_s puts the SYNC late in the period and the
    # conversion is taken at the period after next (a 2 kHz period is shorter than SYNC -> module -> loop here)
    accel_delay_periods: int = _f(1, "", ge=1, le=4)
    # the transducer amplifier: asked at serial_rate_hz (its line carries up to about 1 kHz: a frame of about 75
    # bytes takes 0.8 ms at 921600 baud; the stroke serves the slow centring and the limits), its frame in
    # serial_latency_s after its sample; held between frames
    serial_rate_hz: float = _f(500.0, "Hz", gt=0, le=10000)
    serial_latency_s: float = _f(0.0008, "s", ge=0, le=1)
    # the transducer asked on the loop's grid: serial_offset_s after a period starts (modulo the period), every
    # whole number of periods (at most serial_rate_hz), when the period's other traffic leaves the CPUs free
    # (drivers/README.md: the serial round trip); -1: at its own rate, whatever the phase
    serial_offset_s: float = _f(-1.0, "s", ge=-1, le=0.1)


@dataclass(frozen=True)
class HilConfig:
    """`rig hil`: the emulated rig behind the real drivers."""
    rate_hz: float = _f(500.0, "Hz", ge=10, le=5000)     # loop rate of HIL runs (Modbus, one GIL limit it)
    seconds: float = _f(10.0, "s", gt=0, le=86400)       # isolation off, then on: half each
    settle_s: float = _f(1.0, "s", ge=0, le=3600)        # discarded at the start of each half
    # HIL runs on a shared dev/CI machine, where the whole VM stops for tens of ms at times, so the staleness
    # limit and the loop watchdog of HIL runs sit above such stalls (the hardware keeps [safety] watchdog_s = 50 ms)
    stale_s: float = _f(0.1, "s", gt=0, le=10)           # staleness limit of HIL runs (drivers and safety)
    watchdog_s: float = _f(0.1, "s", gt=0, le=10)        # loop watchdog of HIL runs (safety.watchdog_s)
    lag_limit_s: float = _f(0.1, "s", gt=0, le=10)       # lag limit of HIL runs (safety.lag_limit_s)
    # the emulated serial amplifier's own limit: its pty's bytes wait for a normal-priority kernel worker, which
    # the machine's other load holds off for up to 0.5 s (`rig bench stalls`) and more: 4 of 10 commissionings at
    # load 10-15 faulted at 0.5 s; the stroke serves the slow centring (below [controller] blend_hz)
    serial_stale_s: float = _f(1.0, "s", gt=0, le=10)
    # SCHED_FIFO of the emulated devices (0 = normal): above the drivers' I/O processes ([drivers] thread_priority),
    # below the loop: real devices are never held up by the host's drivers
    device_priority: int = _f(60, "", ge=0, le=99)
    # the CAN between the valves' I/O and the emulated valve nodes: binary frames on a local socket (rig_stream,
    # drivers/can_stream.py) or python-can's socketcand text protocol over 127.0.0.1 (drivers/README.md: the cost)
    can_transport: str = _f("rig_stream", "", choices=("rig_stream", "socketcand"))
    # wiring faults to rehearse (drivers/devicemaps/hil_wiring_faults.md), per analog input channel ch0-7 of the
    # emulated module: which signal it carries (0-3 the mounts' table accelerometers, 4-7 the floor's, MOUNTS
    # order: a swap exchanges two), a factor (-1 its sign inverted, 0.10197 an input range in g read as m/s^2)
    # and an offset
    ai_source: tuple[int, ...] = _f((0, 1, 2, 3, 4, 5, 6, 7), "", ge=0, le=7, n=8)
    ai_factor: tuple[float, ...] = _f((1.0,) * 8, "", ge=-100, le=100, n=8)
    ai_offset_mps2: tuple[float, ...] = _f((0.0,) * 8, "m/s^2", ge=-100, le=100, n=8)
    # the sensors' other faults (same table): extra white noise per AI channel (a dead one: ai_factor 0); per
    # channel of the emulated transducer amplifier (mount order) the mount's stroke it carries (a swap), a factor
    # (-1 inverted, 1e-3 a channel ranged in mm read as um, 0 dead), an offset and extra white noise; and a delay
    # of the analog module's signal (the loop's feedback in its band: a slow module's filter, a supervisor's case)
    ai_noise_mps2: tuple[float, ...] = _f((0.0,) * 8, "m/s^2", ge=0, le=100, n=8)
    dt_source: tuple[int, ...] = _f((0, 1, 2, 3), "", ge=0, le=3, n=4)
    dt_factor: tuple[float, ...] = _f((1.0,) * 4, "", ge=-1e4, le=1e4, n=4)
    dt_offset_m: tuple[float, ...] = _f((0.0,) * 4, "m", ge=-2e-3, le=2e-3, n=4)
    dt_noise_m: tuple[float, ...] = _f((0.0,) * 4, "m", ge=0, le=1e-3, n=4)
    extra_delay_s: float = _f(0.0, "s", ge=0, le=0.02)
    # per valve (MOUNTS order; a layout of fewer mounts takes the first): the command at which its spool centres
    # (a null offset), a factor on its flow gain K_Q, and the CAN node number it answers to with [drivers]
    # valve_node_id_base = 1 (the numbers shift with the base): two exchanged = swapped CAN nodes, the driver's
    # command for one mount moves the other
    valve_null_V: tuple[float, ...] = _f((0.0,) * 4, "V", ge=-10, le=10, n=4)
    valve_gain: tuple[float, ...] = _f((1.0,) * 4, "", gt=0, le=100, n=4)
    valve_node_id: tuple[int, ...] = _f((1, 2, 3, 4), "", ge=1, le=124, n=4)


@dataclass(frozen=True)
class StandConfig:
    """The simulated single-actuator test stand (chirp runs on the sim backend): effect switches, 0 = off.
    Names as in docs/MODEL.md (the effect switches)."""
    delay_s: float = _f(0.0, "s", ge=0, le=0.1)                 # transport_delay
    saturation_limit_ma: float = _f(0.0, "mA", ge=0, le=1000)  # valve_saturation
    deadband_width_ma: float = _f(0.0, "mA", ge=0, le=1000)    # valve_deadband
    friction_force_n: float = _f(0.0, "N", ge=0, le=1e7)       # coulomb_friction
    base_frequency_hz: float = _f(0.0, "Hz", ge=0)             # base_resonance
    base_damping_ratio: float = _f(0.03, "", gt=0, lt=1)
    base_mass_kg: float = _f(STAND_BASE_MASS_KG, "kg", ge=0.01, le=1e6)
    disturbance_frequency_hz: float = _f(0.0, "Hz", ge=0)      # periodic_disturbance
    disturbance_force_n: float = _f(0.0, "N", ge=0, le=1e7)
    position_noise_m: float = _f(2e-8, "m", ge=0, le=1e-3)     # transducer noise, rms
    accel_noise_mps2: float = _f(2e-4, "m/s^2", ge=0, le=100)  # accelerometer noise, rms
    seed: int = _f(0, "", ge=0, le=SEED_MAX)
    base_motion_rms_m: float = _f(0.0, "m", ge=0, le=1e-3)     # base_motion: the floor under the stand (band,
                                                               # spectrum, seed of [vibration]); rig run only


@dataclass(frozen=True)
class ControllerConfig:
    """Isolation controller per mount (controllers/isolation.py): PI + two leads + two notches + roll-off on the
    mount's absolute motion (accelerometer blended with the stroke below blend_hz); defaults found by the
    structured optimiser on the discrete loop (controllers/tune.py, `rig design --tune`: ZOH + one period of
    delay at 5 kHz; disk margin >= 2/3 on every mount, at or above the paper's attenuation in every band).
    Corners above the Nyquist frequency are allowed (Tustin maps them inside the unit circle): the leads then
    act as near-differentiators up to Nyquist and the roll-off as its double zero at z = -1."""
    blend_hz: float = _f(0.1, "Hz", gt=0)               # accelerometer / stroke complementary blend
    kp_V_per_m: float = _f(288544, "V/m", gt=0, le=1e10)         # PI proportional gain on the compensated position
    pi_corner_hz: float = _f(26.9524, "Hz", gt=0)       # PI integral corner
    # lead poles and the roll-off may sit above Nyquist: Tustin maps them inside the unit circle (see above)
    lead1_zero_hz: float = _f(5.56773, "Hz", gt=0)
    lead1_pole_hz: float = _f(5000, "Hz", gt=0, le=1e6, nyquist=False)
    lead2_zero_hz: float = _f(26.8104, "Hz", gt=0)
    lead2_pole_hz: float = _f(5000, "Hz", gt=0, le=1e6, nyquist=False)
    rolloff_hz: float = _f(5000, "Hz", ge=0, le=1e6, nyquist=False)   # second-order low-pass (0 = none)
    rolloff_zeta: float = _f(0.334788, "", gt=0, le=10)
    notch_hz: float = _f(229.856, "Hz", ge=0)           # optional notch (0 = none)
    notch_zeta_zero: float = _f(0.427624, "", ge=0, le=10)
    notch_zeta_pole: float = _f(2.26149, "", gt=0, le=10)
    notch2_hz: float = _f(97.368, "Hz", ge=0)           # optional second notch, or peak (zeta_zero > zeta_pole)
    notch2_zeta_zero: float = _f(0.0984906, "", ge=0, le=10)
    notch2_zeta_pole: float = _f(0.0353757, "", gt=0, le=10)
    # floor-motion feedforward (controllers/feedforward.py): inverse actuator model on the floor accelerometer
    ff_hp_hz: float = _f(0.1, "Hz", gt=0)              # floor accelerometer high-pass (double integration)
    ff_lowpass_hz: float = _f(600.0, "Hz", gt=0)       # roll-off of the inverse (6th-order Butterworth)
    ff_gain: float = _f(1.0, "", ge=0, le=2)           # trim on the feedforward path (1 = cancel as modelled)
    centring_hz: float = _f(0.02, "Hz", gt=0)            # slow centring crossover while isolation is off
    prewarp_hz: float = _f(200.0, "Hz", gt=0)            # Tustin prewarp of the compensator (phase crossover)
    fade_s: float = _f(0.1, "s", gt=0, le=60)            # bumpless on/off: switching offset decay time
    sat_reset_s: float = _f(0.1, "s", ge=0, le=60)      # isolating at the valve clamp this long: suspend (0 = off)
    sat_resume_s: float = _f(0.5, "s", gt=0, le=60)     # suspended: resume after the estimate is settled this long
    # per-mount multiplier on kp (MOUNTS order): a correction between mounts, not a sign change or an off switch
    gain_trim: tuple[float, ...] = _f((1.0, 1.0, 1.0, 1.0), "", gt=0, le=10, n=len(MOUNTS))
    # actuator reference-tracking PID (paper Fig. 4): Ki/Kp at the actuator lag corner, 100 Hz bandwidth with
    # GM >= 6 dB and PM >= 45 deg, the least transducer noise in the command (controllers/tracking.py
    # tune_tracking at 5 kHz, one period of delay)
    track_kp_V_per_m: float = _f(2.24e6, "V/m", ge=0, le=1e10)
    track_ki_V_per_ms: float = _f(1.044e8, "V/(m s)", ge=0, le=1e13)
    track_kd_Vs_per_m: float = _f(3.83e3, "V s/m", ge=0, le=1e8)
    # derivative filter corner; Tustin without prewarp squeezes a corner above Nyquist below it (stable)
    track_deriv_hz: float = _f(250.0, "Hz", gt=0, le=1e6, nyquist=False)
    # the reference (controllers/tracking.py): feedforward through the actuator's inverse, previewed over the
    # valve's and the loop's delays; rate limit; what share of the clamp a reference may ask for; profile length
    track_ff: float = _f(1.0, "", ge=0, le=1)              # feedforward gain (0 = the PID alone, Fig. 4)
    track_delay_periods: int = _f(1, "", ge=0, le=16)      # loop delay beyond the ZOH (sim/hardware 1)
    track_rate_m_per_s: float = _f(5e-4, "m/s", gt=0, le=1.0)      # reference rate limit (setpoint ramps)
    track_accel_m_per_s2: float = _f(0.03, "m/s^2", gt=0, le=1e3)  # and its acceleration limit (smooth moves)
    track_headroom: float = _f(0.9, "", gt=0, le=1)        # share of valve_limit_V a reference may need
    track_profile_s: float = _f(60.0, "s", gt=0, le=3600)  # longest CSV profile (its table is allocated once)


@dataclass(frozen=True)
class SensorsConfig:
    """Optional sensors beyond the paper's: a floor accelerometer at each mount, the input of the floor-motion
    feedforward (controllers/feedforward.py). On the hardware it sits on further channels of the analog input
    module (drivers/devicemaps/adam6024_modbus.md); the simulated rig gives it its own noise."""
    floor_accel: bool = _f(False, "")                         # fitted (the loop reads and checks it)
    floor_V_per_mps2: float = _f(2.0, "V/(m/s^2)", ge=1e-3, le=1e3)   # sensitivity with its conditioner
    floor_range_mps2: float = _f(5.0, "m/s^2", gt=0, le=1e3)         # plausible range; beyond (or NaN) = fault
    # white noise of the simulated sensor (a seismic accelerometer, ~0.1 ug/sqrt(Hz))
    floor_noise_mps2_per_rthz: float = _f(1e-6, "m/s^2/sqrt(Hz)", ge=0, le=1.0)
    floor_channels: tuple[int, ...] = _f((4, 5, 6, 7), "", ge=4, le=7, n=len(MOUNTS))   # AI channels, MOUNTS order


@dataclass(frozen=True)
class PlantErrorConfig:
    """The simulated rig's actuators as factors on the configured model (1 = as modelled): the plant the
    controllers and the feedforward meet when their model is wrong (Eq. 11's x_d). Simulated plants only.
    Within a factor of two: further off is another actuator, not a model error."""
    K_L: float = _f(1.0, "", ge=0.5, le=2.0)
    C: float = _f(1.0, "", ge=0.5, le=2.0)
    w_nv: float = _f(1.0, "", ge=0.5, le=2.0)
    zeta: float = _f(1.0, "", ge=0.5, le=2.0)
    K_Q: float = _f(1.0, "", ge=0.5, le=2.0)
    K_C: float = _f(1.0, "", ge=0.5, le=2.0)


@dataclass(frozen=True)
class SupervisorConfig:
    """The do-no-harm supervisor (rig/runtime/supervisor.py): while isolation is on it compares the table's
    vibration (its accelerometers, band_low_hz-band_high_hz, rms over window_s) with its reference: the same
    measured with isolation off (the table over the floor where floor accelerometers are fitted, so that a
    change of the floor is not taken for harm), else the floor itself. Worse by more than margin_db for hold_s:
    one line, an event, isolation off (bumpless) and held off for the rest of the run.
    margin_db = 3 dB (twice the vibration power): on the emulated rig a right design measures 7-17 dB better than
    isolation off and one mount with feedback of the wrong sign 7.5 dB worse on that mount (docs/COMMISSIONING.md,
    measured by the commands there); the harm the rig must not do adds 4-10 dB or grows."""
    enabled: bool = _f(True, "")
    # displacement: what `rig hil` states isolation in; feedback that takes it down lifts the acceleration above
    # its crossover, which a comparison of accelerations would call harm (docs/COMMISSIONING.md)
    quantity: str = _f("displacement", "", choices=("acceleration", "velocity", "displacement"))
    band_low_hz: float = _f(1.0, "Hz", gt=0, le=1e4, nyquist=False)
    band_high_hz: float = _f(100.0, "Hz", gt=0, le=1e4, nyquist=False)   # clipped to 0.45 x the loop's rate
    window_s: float = _f(2.0, "s", ge=0.5, le=60)          # moving window of the rms
    margin_db: float = _f(3.0, "dB", gt=0, le=40)          # worse than the reference by more = harm
    hold_s: float = _f(0.5, "s", ge=0, le=60)             # for this long (checked at 10 Hz)
    settle_s: float = _f(0.5, "s", ge=0, le=60)           # after isolation switches: not compared


@dataclass(frozen=True)
class RigErrorConfig:
    """The simulated four-mount rig as it really is, off the model (1 / 0 / empty = as modelled): what a
    physical rig may hide from its model (issue 28) and what the diagnosis of a run recording names (rig
    diagnose on a `rig run --record` file). Simulated plants only; the controllers keep the configured model.
    Machine: factors on each flexible mode's frequency and damping (modal model order; empty: all 1) and a mode
    the model lacks (extra_mode_hz > 0, its shape at the four mounts in the modal model's unit). Mounts: factors
    on each mount's membrane stiffness K_L and viscous coefficient C (Eq. 7). Sensors: each mount's
    accelerometer, stroke transducer and floor accelerometer sensitivity as a factor (negative: wired with the
    sign reversed). Valves: each actuator's transport delay, spool deadband (overlap, Eq. 1's x_v) and null
    offset (a constant added to the command before the valve amplifier)."""
    mode_frequency_factor: tuple[float, ...] = _f((), "", gt=0.2, le=5.0)
    mode_damping_factor: tuple[float, ...] = _f((), "", gt=0.05, le=20.0)
    extra_mode_hz: float = _f(0.0, "Hz", ge=0, le=2000, nyquist=False)      # 0: none
    extra_mode_damping: float = _f(0.03, "", gt=0, lt=1)
    extra_mode_shape: tuple[float, ...] = _f((0.0, 0.0, 0.0, 0.0), "", ge=-10, le=10, n=len(MOUNTS))
    mount_stiffness_factor: tuple[float, ...] = _f((1.0,) * len(MOUNTS), "", gt=0.05, le=20, n=len(MOUNTS))
    mount_damping_factor: tuple[float, ...] = _f((1.0,) * len(MOUNTS), "", ge=0, le=1e4, n=len(MOUNTS))
    accel_gain: tuple[float, ...] = _f((1.0,) * len(MOUNTS), "", ge=-10, le=10, n=len(MOUNTS))
    stroke_gain: tuple[float, ...] = _f((1.0,) * len(MOUNTS), "", ge=-10, le=10, n=len(MOUNTS))
    floor_gain: tuple[float, ...] = _f((1.0,) * len(MOUNTS), "", ge=-10, le=10, n=len(MOUNTS))
    valve_delay_s: tuple[float, ...] = _f((0.0,) * len(MOUNTS), "s", ge=0, le=0.1, n=len(MOUNTS))
    valve_deadband_ma: tuple[float, ...] = _f((0.0,) * len(MOUNTS), "mA", ge=0, le=100, n=len(MOUNTS))
    valve_null_V: tuple[float, ...] = _f((0.0,) * len(MOUNTS), "V", ge=-10, le=10, n=len(MOUNTS))


@dataclass(frozen=True)
class Config:
    actuator: ActuatorConfig = field(default_factory=ActuatorConfig)
    valve: ValveConfig = field(default_factory=ValveConfig)
    fluid: FluidConfig = field(default_factory=FluidConfig)
    machine: MachineConfig = field(default_factory=MachineConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    backend: BackendConfig = field(default_factory=BackendConfig)
    vibration: VibrationConfig = field(default_factory=VibrationConfig)
    stand: StandConfig = field(default_factory=StandConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    drivers: DriversConfig = field(default_factory=DriversConfig)
    hil: HilConfig = field(default_factory=HilConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    sensors: SensorsConfig = field(default_factory=SensorsConfig)
    plant_error: PlantErrorConfig = field(default_factory=PlantErrorConfig)
    rig_error: RigErrorConfig = field(default_factory=RigErrorConfig)
    layout: LayoutConfig = field(default_factory=LayoutConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    source: str = "<defaults: Table 1>"        # where it came from, for messages

    def replace(self, **sections) -> "Config":
        return dataclasses.replace(self, **sections)


def _check_value(where: str, name: str, ftype, meta, value):
    """Return value converted to ftype, or raise ConfigError naming where.name."""
    origin = typing.get_origin(ftype)
    if ftype is float or ftype == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}.{name}: expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ConfigError(f"{where}.{name}: expected a finite number, got {value!r}")
    elif ftype is int or ftype == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}.{name}: expected an integer, got {value!r}")
    elif ftype is bool or ftype == "bool":
        if not isinstance(value, bool):
            raise ConfigError(f"{where}.{name}: expected true or false, got {value!r}")
    elif ftype is str or ftype == "str":
        if not isinstance(value, str):
            raise ConfigError(f"{where}.{name}: expected a string, got {value!r}")
    elif origin is tuple and typing.get_args(ftype)[:1] == (int,):
        if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            raise ConfigError(f"{where}.{name}: expected a list of integers, got {value!r}")
        value = tuple(value)
    elif origin in (list, tuple) and typing.get_args(ftype)[:1] == (str,):
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{where}.{name}: expected a list of names, got {value!r}")
        value = tuple(value)
    elif origin in (list, tuple) or ftype in ("list[float]", "tuple[float, ...]"):
        if not isinstance(value, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                  for v in value):
            raise ConfigError(f"{where}.{name}: expected a list of numbers, got {value!r}")
        value = tuple(float(v) for v in value)
        if not all(math.isfinite(v) for v in value):
            raise ConfigError(f"{where}.{name}: expected finite numbers, got {list(value)!r}")
    if isinstance(value, tuple):
        if meta.get("n") is not None and len(value) != meta["n"]:
            raise ConfigError(f"{where}.{name}: expected a list of {meta['n']} numbers (one per mount: "
                              f"{', '.join(MOUNTS)}), got {len(value)}: {list(value)!r}")
    unit = f" {meta['unit']}" if meta.get("unit") and meta["unit"] != "path" else ""
    for key, ok, word in (("gt", lambda v, b: v > b, ">"), ("ge", lambda v, b: v >= b, ">="),
                          ("lt", lambda v, b: v < b, "<"), ("le", lambda v, b: v <= b, "<=")):
        bound = meta.get(key)
        if bound is None or isinstance(value, (bool, str)):
            continue
        for v in (value if isinstance(value, tuple) else (value,)):
            if not ok(v, bound):
                got = f"{v!r}" if not isinstance(value, tuple) else f"{v!r} in {list(value)!r}"
                raise ConfigError(f"{where}.{name}: expected {word} {bound:g}{unit}, got {got}")
    if meta.get("choices") and value not in meta["choices"]:
        raise ConfigError(f"{where}.{name}: expected one of {', '.join(meta['choices'])}, got {value!r}")
    return value


def check_actuator_value(where: str, name: str, value: float) -> float:
    """An eha actuator parameter (sim_backend.linear.ActuatorParams' name, e.g. a plant file's K_L) held to the
    range of its key in [actuator], [valve] or [fluid]: one ConfigError naming where.name."""
    for cls in (ActuatorConfig, ValveConfig, FluidConfig):
        field = next((f for f in dataclasses.fields(cls) if f.name == name), None)
        if field is not None:
            return _check_value(where, name, float, field.metadata, value)
    return value


def _build_section(cls, data: dict, where: str):
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table [{where.split(': ')[-1]}], got {data!r}")
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in dataclasses.fields(cls)}
    for key in data:
        if key not in known:
            raise ConfigError(f"{where}.{key}: unknown key (known: {', '.join(known)})")
    kwargs = {}
    for key, value in data.items():
        f = known[key]
        kwargs[key] = _check_value(where, key, hints[key], f.metadata, value)
    return cls(**kwargs)


def config_from_dict(data: dict, source: str = "<dict>") -> Config:
    """Build and validate a Config from parsed TOML."""
    hints = typing.get_type_hints(Config)
    sections = {f.name for f in dataclasses.fields(Config) if f.name != "source"}
    kwargs = {}
    for name, value in data.items():
        if name not in sections:
            raise ConfigError(f"{source}: [{name}]: unknown section (known: {', '.join(sorted(sections))})")
        kwargs[name] = _build_section(hints[name], value, f"{source}: {name}")
    cfg = Config(**kwargs, source=source)
    _check_cross(cfg)
    return cfg


def _check_cross(cfg: Config) -> None:
    """Checks that involve more than one key."""
    v = cfg.vibration
    if v.band_hi_hz <= v.band_lo_hz:
        raise ConfigError(f"{cfg.source}: vibration.band_hi_hz: expected > band_lo_hz ({v.band_lo_hz} Hz), "
                          f"got {v.band_hi_hz}")
    if cfg.safety.valve_limit_V > cfg.valve.max_V:
        raise ConfigError(f"{cfg.source}: safety.valve_limit_V: expected <= valve.max_V ({cfg.valve.max_V} V), "
                          f"got {cfg.safety.valve_limit_V}")
    if cfg.safety.stroke_limit_m > cfg.actuator.stroke_m:
        raise ConfigError(f"{cfg.source}: safety.stroke_limit_m: expected <= actuator.stroke_m "
                          f"({cfg.actuator.stroke_m} m), got {cfg.safety.stroke_limit_m}")
    _check_sensors(cfg)
    _check_rig_error(cfg)
    if cfg.safety.stroke_limit_m > cfg.safety.stroke_range_m:      # a limit the transducer cannot see
        raise ConfigError(f"{cfg.source}: safety.stroke_limit_m: expected <= safety.stroke_range_m "
                          f"({cfg.safety.stroke_range_m} m), got {cfg.safety.stroke_limit_m}")
    check_nyquist(cfg, cfg.loop.rate_hz)
    _check_layout(cfg)
    if cfg.machine.modal_model:
        p = Path(cfg.machine.modal_model)
        if not p.is_absolute() and cfg.source not in ("<defaults: Table 1>", "<dict>"):
            p = Path(cfg.source).parent / p
        if not p.is_file():
            raise ConfigError(f"{cfg.source}: machine.modal_model: file not found: {p}")


def _check_sensors(cfg: Config) -> None:
    """The floor accelerometers: one analog channel each (ch4-7: ch0-3 are the mount accelerometers); the
    range within the module's +-10 V."""
    s = cfg.sensors
    ch = s.floor_channels
    if len(set(ch)) != len(ch):
        raise ConfigError(f"{cfg.source}: sensors.floor_channels: expected {len(MOUNTS)} distinct analog input "
                          f"channels (one per mount), got {list(ch)}")
    if s.floor_range_mps2 * s.floor_V_per_mps2 > 10.0:
        raise ConfigError(f"{cfg.source}: sensors.floor_range_mps2: expected <= 10 V / floor_V_per_mps2 "
                          f"({10.0 / s.floor_V_per_mps2:g} m/s^2, the module's input range), "
                          f"got {s.floor_range_mps2}")


def _check_rig_error(cfg: Config) -> None:
    """A sensor of zero sensitivity reads nothing: a gain is at least 0.05 in size (either sign)."""
    e = cfg.rig_error
    for key in ("accel_gain", "stroke_gain", "floor_gain"):
        g = getattr(e, key)
        if any(abs(x) < 0.05 for x in g):
            raise ConfigError(f"{cfg.source}: rig_error.{key}: expected a sensitivity factor of size >= 0.05 "
                              f"(negative: sign reversed), got {list(g)}")


def _check_layout(cfg: Config) -> None:
    lay = cfg.layout
    names = lay.mounts
    where = f"{cfg.source}: layout.mounts"
    if lay.plant == "machine" and names and tuple(names) != MOUNTS:
        raise ConfigError(f"{where}: the machine stands on the four mounts of its modal model "
                          f"({', '.join(MOUNTS)}), got {list(names)}")
    if names and not 1 <= len(names) <= MAX_MOUNTS:
        raise ConfigError(f"{where}: expected 1 to {MAX_MOUNTS} names, got {len(names)}")
    bad = [m for m in names if not m or not m.replace("_", "").isalnum()]
    if bad:
        raise ConfigError(f"{where}: expected names of letters, digits and _, got {bad[0]!r}")
    if len(set(names)) != len(names):
        raise ConfigError(f"{where}: a name appears twice in {list(names)}")


def layout_mounts(cfg: Config) -> tuple[str, ...]:
    """The mount names of the configured layout: [layout] mounts, else the machine's four or one stand."""
    if cfg.layout.mounts:
        return tuple(cfg.layout.mounts)
    return MOUNTS if cfg.layout.plant == "machine" else ("stand",)


NYQUIST_SECTIONS = ("controller", "vibration", "stand", "safety")
F_MIN_HZ = 1e-3          # a slower "frequency" (a period over 15 min) is a constant within any run


def check_nyquist(cfg: Config, rate_hz: float, *, sections=NYQUIST_SECTIONS, rate_source: str | None = None) -> None:
    """Every frequency in Hz of `sections` (except the rates themselves; 0 = off) below rate_hz / 2: a
    discrete filter or a floor band cannot hold a frequency at or above Nyquist (a notch there turns into a
    limit cycle, a band-pass design fails); and not below F_MIN_HZ. ConfigError naming the key and the rate."""
    nyq = rate_hz / 2
    src = rate_source or f"loop.rate_hz = {rate_hz:g} Hz"
    for sec in sections:
        obj = getattr(cfg, sec)
        for f in dataclasses.fields(obj):
            if f.metadata.get("unit") != "Hz" or f.name.endswith("rate_hz") or not f.metadata.get("nyquist"):
                continue
            v = getattr(obj, f.name)
            if 0 < v < F_MIN_HZ:
                off = "0 (off) or " if f.metadata.get("ge") == 0 else ""
                raise ConfigError(f"{cfg.source}: {sec}.{f.name}: expected {off}>= {F_MIN_HZ:g} Hz, got {v:g}")
            if v > 0 and not v < nyq:
                raise ConfigError(f"{cfg.source}: {sec}.{f.name}: expected < {nyq:g} Hz (the Nyquist frequency "
                                  f"of {src}), got {v:g}")


def load_config(path: str | Path | None) -> Config:
    """Load FILE, or the Table 1 defaults when path is None."""
    if path is None:
        return Config()
    p = Path(path)
    text = read_text(p, "config file", ConfigError)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: invalid TOML: {e}") from None
    return config_from_dict(data, source=str(p))


def hil_run_config(cfg: Config, rate_hz: float | None = None) -> Config:
    """The config of a run against the emulated rig: the loop at rate_hz (default [hil] rate_hz), the safety
    checks with the [hil] staleness limit, watchdog and lag limit."""
    rate = float(rate_hz or cfg.hil.rate_hz)
    # the emulated floor runs at the HIL rate too
    check_nyquist(cfg, rate, sections=("vibration",), rate_source=f"the HIL loop at {rate:g} Hz")
    return cfg.replace(loop=dataclasses.replace(cfg.loop, rate_hz=rate),
                       safety=dataclasses.replace(cfg.safety, stale_s=cfg.hil.stale_s,
                                                  watchdog_s=cfg.hil.watchdog_s, lag_limit_s=cfg.hil.lag_limit_s))


def channel_delays(cfg: Config, rate_hz: float | None = None) -> tuple[int, int]:
    """The delay in loop periods from a sensor's sample to the command it changes acting, per channel, through
    the drivers' timing ([drivers]): the accelerometers' conversion at SYNC k reaches the commands sent with SYNC
    k + accel_delay_periods, or with blocks of conversions (accel_fetch_every) the last of the block; the
    transducer's sample is held between frames (serial_rate_hz) and arrives serial_latency_s after it was taken. (accel, stroke); the
    controller design (controllers/tune_hil.py) and the lockstep simulation of the same timing use them."""
    rate = float(rate_hz or cfg.loop.rate_hz)
    d = cfg.drivers
    accel = d.accel_delay_periods - 1 + d.accel_fetch_every
    age = d.serial_latency_s + 0.5 / d.serial_rate_hz          # the transducer sample's mean age when used
    return accel, max(1, 1 + int(math.floor(age * rate + 0.5)))


def modal_model_path(cfg: Config) -> Path | None:
    """Resolved path of the user's modal model file, or None for the embedded one."""
    if not cfg.machine.modal_model:
        return None
    p = Path(cfg.machine.modal_model)
    if not p.is_absolute() and cfg.source not in ("<defaults: Table 1>", "<dict>"):
        p = Path(cfg.source).parent / p
    return p
