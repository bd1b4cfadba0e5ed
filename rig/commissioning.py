"""Commissioning analysis: a recording of open-loop valve excitation, one valve at a time, checked channel by
channel (`rig commission`, rig/commands/commission.py runs it).

The recording: `quiet_s` with every valve at null (noise floor and offset of every channel), then per mount a slot
of `slot_s`: its valve a bounded chirp, the others null. Per slot j and channel i (band-passed to `BAND_HZ`,
where the transducer's second derivative and the accelerometers are both above their noise):

  stroke response   rms of stroke channel i in slot j          -> which transducer answers which valve
  accel response    rms of accel i in slot j                   -> which accelerometer answers which valve
  accel scale       S(x_j'', a_i) / S(x_j'', x_j'') in band  -> sign and scale against the second derivative of
                    (a: the table's accelerometer, less the      its own mount's stroke (table = floor + stroke:
                    floor once checked; x_j: the stroke          the floor accelerometers take the floor out)
                    answering valve j)
  floor scale       floor channel k = c a_p + d x_p'' per        -> each floor accelerometer's sign, scale and
                    frequency over the whole recording, c        mount (floor_response: the table less its own
                    averaged over the band                       stroke's x'' is the floor under it)
  valve gain        the stroke's chirp response over the command at the low end of the band against the model's
                    DC gain (the actuator's lag corner lies far above it)

Verdicts per channel: ok, corrected (the calibration file puts it right: a swap, a sign, a scale within
SCALE_FIX, a transducer's unit slip, an offset), refused (dead, noisy, or a scale nobody should correct),
unchecked (an accelerometer whose mount's transducer is dead: nothing to hold its sign and scale against).
The sensors' own checks (sensor_findings): alive, offset and noise floor at null, each channel's noise floor
(above NOISE_HZ, where the table barely moves and a sensor's white noise shows) against the median of the
others of its kind, and a transducer's range or unit slip (stroke_unit: its stroke/command a power of ten off the
other mounts', and its accelerometer moved the other way against its x'').

One mount alone (the prototype on its stand): one valve, one transducer, one accelerometer, so nothing can be
swapped and there are no others of its kind to hold a channel against. A dead transducer is judged against the
model's DC gain (its stroke per volt under STROKE_DEAD_RATIO of it), a noise floor against the sensor's own noise
as configured plus its device's resolution (`sensor_noise`, above TOP_FRACTION of the Nyquist frequency).
"""
from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import signal
from scipy.optimize import linear_sum_assignment

BAND_HZ = (3.0, 30.0)          # where x'' from the transducer and the accelerometers are both well above noise
SCALE_TOL = 0.35               # |scale| within 1 +- this: ok (wired right 1.0-1.2 with the floor's motion in the
                               # accelerometer, 1.00-1.04 with it taken out; a g range is 0.10, inverted -1)
SCALE_FIX = (0.05, 20.0)       # |scale| in this range (g against m/s^2, mm against um... ): corrected
NO_ANSWER = SCALE_FIX[0]       # channel_map: a channel whose largest answer is below this x the median channel's
DOCUMENTED = 1.25              # answers nothing; between answers that do not tell, the wiring as documented stands
DEAD_RMS_RATIO = 0.1           # a channel answering its valve less than this of the others' median: dead
# the valves (valve_checks): a null beyond NULL_TOL_V is named and corrected (0.5 % of a +-10 V valve's range: wired
# right the quiet stroke reads about 0.01 V's worth); an apparent null beyond NULL_MAX_V is no valve's but its
# transducer's own offset; the DC gain within 1 +- GAIN_TOL of the model's is ok (wired right 0.92: the table takes
# part of a mount's stroke), within GAIN_FIX corrected, beyond it refused (a broken valve, not a wiring slip)
NULL_TOL_V = 0.05
NULL_MAX_V = 2.0
GAIN_TOL = 0.25
GAIN_FIX = (0.33, 3.0)
STROKE_DEAD_RATIO = 0.02       # the same for a transducer: one whose range is a decade off answers 0.1 of the
                               # others' (a range slip, stroke_unit), a dead one its own noise (< 0.002 measured)
NOISE_HZ = 100.0               # noise floor: a channel's rms at null above this (or 0.3 fs, the lower)
NOISY_RATIO = 3.0              # a noise floor above this x the median of the others of its kind: noisy (refused:
                               # no calibration takes noise out, and the loop would feed it to the valves; channels
                               # wired right lie within a few % of each other)
OFFSET_RATIO = 5.0             # an offset at null above this x the channel's rms there: named (and taken off)
TOP_FRACTION = 0.8             # one mount's noise floor: its rms above this x Nyquist, where the floor's motion
                               # (its band and its filter's tail, 1e-3 m/s^2 rms above 100 Hz on the emulated
                               # stand) has died out and the sensor's white noise is what is left; against the
                               # configured noise NOISY_RATIO holds (no others of its kind to compare with)
HELD_MAX = 0.25                # ... judged only when at most this share of its samples at null repeat the one before
                               # (a live sensor's never do: the host held the loop off, or the transducer's frames
                               # came late, 8-17 % on a loaded host, 82 % under a load of 12 on 2 cores)
QUIET_WINDOW_S = 0.1           # a noise floor is the least rms over windows this long: a sensor's own noise is in
                               # every window, a host's hiccup (late periods, repeats) puts the floor's motion's
                               # steps into some (measured: 2.4e-5 m/s^2 in a clean window, 5.6e-3 in a late one)


def _band(x, fs):
    sos = signal.butter(2, BAND_HZ, btype="bandpass", fs=fs, output="sos")
    return signal.sosfiltfilt(sos, x, axis=0)


UNIT_FACTORS = (9.80665, 1.0 / 9.80665, 1e3, 1e-3, 1e6, 1e-6)    # g against m/s^2, mm/um/m against each other


def unit_slip(a: float) -> bool:
    """|scale| a is a unit's factor off 1 (g against m/s^2, mm/um/m against each other), within SCALE_TOL."""
    return any(abs(a * f - 1) <= SCALE_TOL for f in UNIT_FACTORS)


def correction(scale: float) -> float:
    """The factor the calibration puts on a channel measured at `scale` against its stroke's x'': 1 within the
    tolerance (the table's own flexibility, not the sensor), the unit slip it matches (g against m/s^2 ...),
    else the measured 1/|scale|."""
    a = abs(scale)
    if a == 0 or abs(a - 1) <= SCALE_TOL:
        return 1.0
    for f in UNIT_FACTORS:
        if abs(a * f - 1) <= SCALE_TOL:
            return f
    return 1.0 / a


def stroke_unit(gain_vs_model: float, accel_scale: float, gain_ref: float = 1.0) -> float:
    """The factor that puts a transducer's range or unit slip right (a range a decade off: 10 or 0.1; mm read as
    um: 1e3 ...), else 1. A transducer reading k x its stroke shows twice: its stroke/command reads k x the rig's
    (gain_ref: the other mounts' median over the model's DC gain), and its accelerometer's scale against its x''
    1/k (times the accelerometer's own slip, a g range on the same mount: 0.102/k). The power of ten comes from the
    first (a valve's own gain, within GAIN_FIX, stays inside half a decade); the second must have moved more than
    half way towards it: a valve ten times weak or strong moves the first only, an accelerometer's g range the
    second only."""
    g, a = abs(gain_vs_model) / abs(gain_ref), abs(accel_scale)
    if not (g > 0 and a > 0 and math.isfinite(g) and math.isfinite(a)):
        return 1.0
    decades = -round(math.log10(g))           # the stroke/command against the rig's: 10^-decades = k
    if decades == 0 or math.log10(a) * decades < 0.5 * decades ** 2:
        return 1.0
    return 10.0 ** decades


def _gain_ref(gain: dict, m: str, dead: set) -> float:
    """The rig's stroke/command over the model's, from the mounts other than m (their median; 1 alone)."""
    others = [abs(g) for k, g in gain.items() if k != m and k not in dead and g]
    return float(np.median(others)) if others else 1.0


def noise_floor(x: np.ndarray, fs: float, corner_hz: float | None = None) -> np.ndarray:
    """Each column's rms above corner_hz (default NOISE_HZ or 0.3 fs, the lower: where the table barely moves and
    the sensor's own noise is what is left), the least over windows of QUIET_WINDOW_S: a sensor's noise is in every
    window, a host's hiccup (late periods) only in some. A window in which more than HELD_MAX of the samples repeat
    the one before on every column at once has no noise to measure (the host held the loop off, the device's whole
    frame: a stall of the amplifier's frames read 1.2 nm on a transducer whose other windows read 12-16 nm, and two
    channels beside it were named noisy against it); it is left out unless every window is. (One column's own
    repeats are its resolution: a transducer ranged a decade down reads a few nm in 1 nm steps.)"""
    corner = min(NOISE_HZ, 0.3 * fs) if corner_hz is None else corner_hz
    sos = signal.butter(4, corner, btype="highpass", fs=fs, output="sos")
    y = signal.sosfiltfilt(sos, x - x.mean(axis=0), axis=0)
    w = max(int(round(QUIET_WINDOW_S * fs)), 8)
    k = max(len(y) // w, 1)
    rms = np.sqrt((y[:k * w] ** 2).reshape(k, -1, y.shape[1]).mean(axis=1))
    same = np.concatenate([[False], np.all(np.diff(x, axis=0) == 0, axis=1)])
    held = same[:k * w].reshape(k, -1).mean(axis=1) > HELD_MAX
    return rms.min(axis=0) if held.all() else rms[~held].min(axis=0)


def held_share(x: np.ndarray) -> np.ndarray:
    """Each column's share of samples equal to the one before (repeated, not new)."""
    return (np.diff(x, axis=0) == 0).mean(axis=0)


def top_noise(x: np.ndarray, fs: float) -> np.ndarray:
    """noise_floor above TOP_FRACTION x Nyquist (one mount's noise floor, against sensor_noise)."""
    return noise_floor(x, fs, TOP_FRACTION * fs / 2)


def top_noise_gain(fs: float) -> float:
    """top_noise of unit white noise: sqrt(mean |H|^4) over 0..Nyquist (sosfiltfilt applies |H|^2)."""
    sos = signal.butter(4, TOP_FRACTION * fs / 2, btype="highpass", fs=fs, output="sos")
    _, h = signal.sosfreqz(sos, worN=4096, fs=fs)
    return float(np.sqrt(np.mean(np.abs(h) ** 4)))


def quiet_channels(acc, x, floor, quiet, fs, names, sensor_noise=None) -> dict:
    """Each channel at null: offset, rms, noise floor, alive (accel, stroke; floor where the floor accelerometers
    are fitted). Keyed by the mount each channel is mapped to. sensor_noise ({kind: white noise rms per sample,
    in the loop's units}): each such channel also its noise above TOP_FRACTION x Nyquist (noise_top_*) and what
    that noise alone gives there (noise_spec_*)."""
    kinds = {"accel": (acc, "mps2"), "stroke": (x, "m")}
    if floor is not None:
        kinds["floor"] = (floor, "mps2")
    out = {}
    for kind, (v, unit) in kinds.items():
        q = v[quiet]
        nf = noise_floor(q, fs)
        out[kind] = {m: {f"offset_{unit}": float(q[:, i].mean()), f"noise_rms_{unit}": float(q[:, i].std()),
                         f"noise_floor_{unit}": float(nf[i]), "alive": bool(q[:, i].std() > 0)}
                     for i, m in enumerate(names)}
        if sensor_noise and kind in sensor_noise:
            top = top_noise(q, fs)
            held = held_share(q)
            for i, m in enumerate(names):
                out[kind][m]["held_share"] = float(held[i])
                out[kind][m][f"noise_top_{unit}"] = float(top[i])
                out[kind][m][f"noise_spec_{unit}"] = float(sensor_noise[kind]) * top_noise_gain(fs)
    return out


def sensor_findings(names, channels, accel_of, stroke_of, units, gain_raw, dead_x, verdicts, findings,
                    fix=None, null_window_m: float = 0.0, floor_of=None) -> set:
    """The sensors' checks beside the response matrix (verdicts and findings updated in place): dead, noisy,
    offset at null, a transducer's unit slip. A channel is named as mapped (its [kind.<name>] in the calibration);
    its noise floor is compared as calibrated (fix: {kind: {channel: its scale}}: a range a decade up is not noisy).
    floor_of: the floor channel found under each mount (floor_response; default each its own).
    Returns {(kind:channel, fault)} of what it named."""
    fix = fix or {}
    named = set()
    carries = {"accel": {names[a]: m for a, m in zip(accel_of, names)},
               "stroke": {names[x]: m for x, m in zip(stroke_of, names)},
               "floor": {names[k]: m for k, m in zip(floor_of or range(len(names)), names)}}
    what = {"accel": "accelerometer", "stroke": "transducer", "floor": "floor accelerometer"}
    rank = {"ok": 0, "unchecked": 1, "corrected": 2, "refused": 3}

    def worse(key, v):
        if rank[v] > rank[verdicts.get(key, "ok")]:
            verdicts[key] = v

    for kind, rows in channels.items():
        unit = "m" if kind == "stroke" else "mps2"
        shown = (1e6, "um") if kind == "stroke" else (1e3, "mm/s^2")
        for ch, row in rows.items():
            key = f"{kind}:{carries[kind][ch]}"
            name = f"{what[kind]} channel mapped to {ch}"
            if not row["alive"]:
                worse(key, "refused")
                findings.append(f"{name}: dead (constant at null)")
                named.add((f"{kind}:{ch}", "dead"))
                continue
            floors = {c: r[f"noise_floor_{unit}"] * abs(fix.get(kind, {}).get(c, 1.0)) for c, r in rows.items()}
            # the others of its kind that are sensors: a dead transducer reads the amplifier's own few nm, and two of
            # them would make the median a sensor's noise is held against
            others = [floors[c] for c, r in rows.items() if c != ch and r["alive"]
                      and not (kind == "stroke" and carries[kind][c] in dead_x)]
            nf = floors[ch]
            if others and nf > NOISY_RATIO * float(np.median(others)):
                worse(key, "refused")
                findings.append(f"{name}: noisy, noise floor {nf * shown[0]:.3g} {shown[1]} rms above "
                                f"{NOISE_HZ:g} Hz, {nf / float(np.median(others)):.1f} x the others'")
                named.add((f"{kind}:{ch}", "noisy"))
            elif not others and f"noise_spec_{unit}" in row and row["held_share"] <= HELD_MAX:   # alone: against
                # its own configured noise (analyse notes a channel not judged: its samples held)
                top = row[f"noise_top_{unit}"] * abs(fix.get(kind, {}).get(ch, 1.0))
                spec = row[f"noise_spec_{unit}"]
                if top > NOISY_RATIO * spec:
                    worse(key, "refused")
                    findings.append(f"{name}: noisy, {top * shown[0]:.3g} {shown[1]} rms at the top of the band, "
                                    f"{top / spec:.1f} x its configured noise and resolution")
                    named.add((f"{kind}:{ch}", "noisy"))
            off = row[f"offset_{unit}"]
            # a stroke offset a valve's null explains (within NULL_MAX_V of the DC gain) is the valve's to name
            # (valve_checks): one owner for each offset
            # (read through the channel's unit correction: a range a decade up reads the null's stroke 10 x)
            least = null_window_m / abs(fix.get(kind, {}).get(ch, 1.0) or 1.0) if kind == "stroke" else 0.0
            if abs(off) > max(OFFSET_RATIO * row[f"noise_rms_{unit}"], least):
                worse(key, "corrected")
                findings.append(f"{name}: offset {off * shown[0]:+.4g} {shown[1]} at null (taken off by the "
                                f"calibration)")
                named.add((f"{kind}:{ch}", "offset"))
    for j, m in enumerate(names):
        if units[m] != 1.0:
            worse(f"stroke:{m}", "corrected")
            findings.append(f"transducer of {m} (channel mapped to {names[stroke_of[j]]}): reads {1 / units[m]:g} x "
                            f"its stroke (stroke/command {gain_raw[m]:+.3g} x the model's DC gain, the accelerometer "
                            f"{units[m]:g} x its x''): a range or unit slip, scale {units[m]:g} in the calibration")
            named.add((f"stroke:{names[stroke_of[j]]}", "scale"))
        if m in dead_x:
            worse(f"accel:{m}", "unchecked")
            findings.append(f"accelerometer on {m}: sign and scale not checked (its mount's transducer answers "
                            f"nothing)")
    return named


def sensor_faults(names, accel_of, stroke_of, scale, gain, dead_x, verdicts, named) -> list[dict]:
    """The sensors' faults, one {channel: "<kind>:<channel as mapped>", kind} each (swap, sign, scale, offset, dead,
    noisy), from the response matrix's results and sensor_findings' `named`. A swap is a sensor's only when the
    other sensor of the mount does not answer the same other valve: both moving together is the valve's wiring."""
    out = set(named)
    for j, m in enumerate(names):
        ac, xs = accel_of[j], stroke_of[j]
        valve_moved = ac == xs != j
        a, ch = abs(scale[m]), f"accel:{names[ac]}"
        if verdicts[f"accel:{m}"] != "unchecked" and (ch, "dead") not in out:
            if a < SCALE_FIX[0]:                     # no answer: its sign and its place are its noise's
                out.add((ch, "dead"))
            else:
                if scale[m] < 0:
                    out.add((ch, "sign"))
                if abs(a - 1) > SCALE_TOL:
                    out.add((ch, "scale"))
        if ac != j and not valve_moved and (ch, "dead") not in out:
            out.add((ch, "swap"))
        if m in dead_x:
            out.add((f"stroke:{names[xs]}", "dead"))
            continue
        if xs != j and not valve_moved:
            out.add((f"stroke:{names[xs]}", "swap"))
        if gain[m] < 0:
            out.add((f"stroke:{names[xs]}", "sign"))
    return [{"channel": c, "kind": k} for c, k in sorted(out)]


def channel_map(R: np.ndarray, own=None) -> list[int]:
    """Which channel answers which valve: each channel's responses over its own mean (a channel's scale, wrong or
    not, cancels: a g range answers as clearly as a right one), the valves given channels one to one by the best
    total (scipy's assignment). R[channel, valve]; own: the channel each valve has as documented (default the
    valve's index); returns the channel of each valve.
    - With fewer valves than channels (the floor's map over the mounts that can hold it) some channels are left
      out: over its own largest, a channel that answers none of them (its mount left out) read 1 on some valve and
      took that valve's channel (the floor under a mount with a dead transducer named swapped, twice in `rig prove
      --commission`); over its mean it reads flat, below a channel that answers its own.
    - A channel that answers nothing (its largest below NO_ANSWER x the channels' median: dead, unwired) holds no
      evidence: 1 on every valve, not 0 (a dead floor channel, cost without end on every mount, was left out and a
      flat channel took its mount).
    - Between answers that do not tell (flat rows, dead channels) the wiring as documented stands: its channel's
      answer counts DOCUMENTED x. A real swap moves a channel's answer by about 2 x (the floor: 1.05 under its
      mount, 0.4-0.6 under the others; the valves' chirps far more), a flat row by a few %.
    In a square R any per-channel factor cancels."""
    R = np.asarray(R, dtype=float)
    own = list(range(R.shape[1])) if own is None else list(own)
    top = R.max(axis=1)
    rel = R / np.maximum(R.mean(axis=1, keepdims=True), 1e-300)
    rel[top < NO_ANSWER * np.median(top)] = 1.0
    for j, k in enumerate(own):
        rel[k, j] *= DOCUMENTED
    rows, cols = linear_sum_assignment(-np.log(np.maximum(rel, 1e-12)))
    out = [0] * R.shape[1]
    for i, j in zip(rows, cols):
        out[j] = int(i)
    return out


def _sensor_calibration(names, accel_of, stroke_of, mount_of, scale, gain, units, channels) -> dict:
    """The calibration's sensor tables: per channel as mapped the mount it carries, its sign, scale and offset."""
    return {"accel": {names[accel_of[j]]: {"mount": names[mount_of[j]], "sign": 1.0 if scale[m] >= 0 else -1.0,
                                           "scale": correction(scale[m]),
                                           "offset_mps2": channels["accel"][names[accel_of[j]]]["offset_mps2"]}
                      for j, m in enumerate(names)},
            "stroke": {names[stroke_of[j]]: {"mount": names[mount_of[j]], "sign": 1.0 if gain[m] >= 0 else -1.0,
                                             "scale": units[m],
                                             "offset_m": channels["stroke"][names[stroke_of[j]]]["offset_m"]}
                       for j, m in enumerate(names)}}


def _against_stroke(scale, gain, units, dead_x) -> None:
    """Each accelerometer's scale (as measured against its stroke's x'', in place) against the stroke as
    calibrated: its unit and sign put right (gain: the stroke/command with its unit put right)."""
    for m in scale:
        scale[m] = 1.0 if m in dead_x else scale[m] / units[m] * (1.0 if gain[m] >= 0 else -1.0)


def floor_pass(names, fs, sel, slots, ab, xdd, fb, cb, xb, accel_of, stroke_of, mount_of, scale, gain, units,
               channels, dc_gain_m_per_V, dead_x) -> tuple[dict, dict]:
    """With floor accelerometers: each checked against the table (floor_response: the table's accelerometers at
    the sign and unit slip their first scale found, the strokes as calibrated), then the floor as each channel
    found under a mount reads it (its sign, a unit's slip) taken out of that mount's table accelerometer, and the
    accelerometers' scales against x'' measured again. In a 2 s chirp the floor's motion (about 11 mm/s^2 rms in
    BAND_HZ on the emulated rig, as much as a valve's x'') is most of the scatter of that estimate: measured
    1.00-1.03 with it taken out, 0.98-1.36 with it in, the same recording. A mount whose floor channel does not
    answer as wired right, or a unit's slip, keeps its first estimate. Returns floor_response's result and the raw
    scales (before _against_stroke)."""
    k_a = {m: 1.0 / correction(scale[m]) if unit_slip(abs(scale[m])) else 1.0 for m in names}
    cal = {"accel": {names[accel_of[j]]: {"sign": 1.0 if scale[m] >= 0 else -1.0, "scale": 1.0 / k_a[m]}
                     for j, m in enumerate(names)},
           "stroke": {names[stroke_of[j]]: {"sign": 1.0 if gain[m] >= 0 else -1.0, "scale": units[m]}
                      for j, m in enumerate(names)}}
    # the floor under a mount is held against its table only where the table's accelerometer and transducer answer
    table = [mount_of[j] for j, m in enumerate(names) if m not in dead_x and abs(scale[m]) >= SCALE_FIX[0]
             and channels["accel"][names[accel_of[j]]]["alive"]]
    flo = floor_response(names, fs, sel, ab, xdd, fb, accel_of, stroke_of, mount_of, cal, table)
    rel = ab.copy()
    for j, m in enumerate(names):
        p = mount_of[j]
        k, c = flo["floor_of"][p], flo["scale"][names[p]]
        if p in table and channels["floor"][names[k]]["alive"] and (abs(abs(c) - 1) <= SCALE_TOL or unit_slip(abs(c))):
            floor_p = fb[:, k] * (1.0 if c >= 0 else -1.0) * (correction(c) if unit_slip(abs(c)) else 1.0)
            rel[:, accel_of[j]] -= floor_p * cal["accel"][names[accel_of[j]]]["sign"] * k_a[m]
    raw, _ = _scale_and_gain(names, slots, xdd, rel, cb, xb, stroke_of, accel_of, fs, dc_gain_m_per_V)
    return flo, raw


def floor_response(names, fs, sel, ab, xdd, fb, accel_of, stroke_of, mount_of, cal, table=None) -> dict:
    """The floor accelerometers against the table. table = floor + stroke at each mount (the identity the
    accelerometers' scale check uses, the other way round): the floor under mount p is its table accelerometer a_p
    less its stroke's x''_p, both as calibrated (their channel map, sign and scale). The chirps move the table, not
    the floor: the floor's own motion (part of it common to the mounts, part each mount's own) is the signal, over
    the whole recording (sel) in BAND_HZ. Per frequency, floor channel k = c a_p + d x''_p (two inputs, H1): the
    transducer's later sample (0-2 samples under load) turns d's phase, not c, and any share of x''_p the table
    accelerometer reads other than 1 goes into d; c, averaged over the band, is the channel's scale against the floor
    under p (1 wired right), its sign from the real part. Which channel is under which mount: the response matrix
    |c| (channel_map, as the valves' channels) over the mounts in `table` (default all: those whose table
    accelerometer and transducer answer; a dead one's column is noise), the others' channels left to them in order.
    Returns H[k, p] = c, floor_of (the channel under each mount) and scale (each mount's c through its channel)."""
    n = len(names)
    a, xs = np.zeros((int(sel.sum()), n)), np.zeros((int(sel.sum()), n))
    for j in range(n):
        ca, cx = cal["accel"][names[accel_of[j]]], cal["stroke"][names[stroke_of[j]]]
        a[:, mount_of[j]] = ab[sel, accel_of[j]] * ca["sign"] * ca["scale"]
        xs[:, mount_of[j]] = xdd[sel, stroke_of[j]] * cx["sign"] * cx["scale"]
    z = np.column_stack([a, xs, fb[sel]])
    f, S = signal.csd(z[:, :, None], z[:, None, :], fs=fs, nperseg=min(512, len(z)), axis=0)    # S[f, i, j]
    S = S[(f >= BAND_HZ[0]) & (f <= BAND_HZ[1])]
    H = np.zeros((n, n))
    for p in range(n):
        G = S[:, [p, n + p]][:, :, [p, n + p]]                  # [[S_aa, S_ax], [S_xa, S_xx]] per frequency
        for k in range(n):
            c = np.linalg.solve(G, S[:, [p, n + p], 2 * n + k][..., None])[:, 0, 0].mean()
            H[k, p] = abs(c) * (1.0 if c.real >= 0 else -1.0)
    table = list(range(n)) if table is None else sorted(table)
    floor_of = list(range(n))
    if table:
        found = channel_map(np.abs(H[:, table]), own=table)
        left = iter(k for k in range(n) if k not in found)
        floor_of = [found[table.index(p)] if p in table else next(left) for p in range(n)]
    return {"H": H, "floor_of": floor_of, "scale": {m: float(H[floor_of[p], p]) for p, m in enumerate(names)}}


def floor_checks(names, flo, channels, cal, verdicts, findings, named, mount_of, means) -> set:
    """Per mount, the floor accelerometer floor_response found under it: ok, corrected (swapped channels, a sign,
    a unit's slip: as the table's accelerometers, SCALE_TOL and unit_slip), refused (no answer to the floor's motion
    or a scale no unit's slip explains), unchecked (the mount's table accelerometer or transducer refused or
    unchecked: nothing to hold it against). Verdicts ("floor:<mount>"), findings and cal["floor"] updated in place;
    returns the faults {("floor:<channel as mapped>", kind)}. An offset is taken off only where sensor_findings
    named one, at the channel's mean over the whole recording (means): the floor feedforward integrates its input
    twice (controllers/feedforward.py, 0.1 Hz high-pass), and the mean of the quiet 1.2 s (the floor's own motion,
    up to 0.25 mm/s^2) taken off as an offset wound its command up to 18 V and onto the valves' clamp."""
    rank = {"ok": 0, "unchecked": 1, "corrected": 2, "refused": 3}
    held = {mount_of[j] for j, m in enumerate(names)
            if {verdicts[f"accel:{m}"], verdicts[f"stroke:{m}"]} & {"refused", "unchecked"}}
    out, cal["floor"] = set(), {}
    for p, m in enumerate(names):
        k = flo["floor_of"][p]
        ch, s = names[k], flo["scale"][m]
        name = f"floor accelerometer under {m} (channel mapped to {ch})"
        v = "ok"
        cal["floor"][ch] = {"mount": m, "sign": 1.0, "scale": 1.0,
                            "offset_mps2": float(means[k]) if (f"floor:{ch}", "offset") in named else 0.0}
        if p in held:
            v = "unchecked"
            findings.append(f"{name}: not checked (the table's accelerometer or transducer of {m} is not right)")
        elif (f"floor:{ch}", "dead") in named:
            v = "refused"                                       # sensor_findings named it (constant at null)
        elif abs(s) < SCALE_FIX[0]:
            v = "refused"
            out.add((f"floor:{ch}", "dead"))
            findings.append(f"{name}: no answer to the floor's motion (scale {s:+.3g} against the table less its "
                            f"stroke's x''): dead or unwired")
        else:
            if k != p:
                v = "corrected"
                out.add((f"floor:{ch}", "swap"))
                findings.append(f"floor accelerometers swapped: the floor under {m} is read by the channel mapped "
                                f"to {ch}")
            if s < 0:
                v = "corrected"
                out.add((f"floor:{ch}", "sign"))
                findings.append(f"{name}: sign inverted (scale {s:+.3f} against the table less its stroke's x'')")
            a = abs(s)
            if abs(a - 1) > SCALE_TOL:
                out.add((f"floor:{ch}", "scale"))
                v = "corrected" if SCALE_FIX[0] <= a <= SCALE_FIX[1] and unit_slip(a) else "refused"
                findings.append(f"{name}: scale {a:.3f} against the table less its stroke's x''" +
                                ("" if v == "corrected" else " is no unit slip: not corrected; check the sensor"))
            cal["floor"][ch].update(sign=1.0 if s >= 0 else -1.0, scale=correction(s) if v != "refused" else 1.0)
        verdicts[f"floor:{m}"] = max(v, verdicts.get(f"floor:{m}", "ok"), key=rank.get)   # noisy: refused
    return out


def _responses(t, xb, rb, quiet_s: float, slot_s: float, lead_s: float):
    """Each valve's chirp slot (its settled part), and the stroke and accelerometer channels' band rms in each:
    R[channel, valve]."""
    n = xb.shape[1]
    R_x, R_a = np.zeros((n, n)), np.zeros((n, n))
    slots = []
    for j in range(n):
        t0 = quiet_s + j * slot_s + lead_s
        sl = (t > t0 + 0.1) & (t < t0 + slot_s - 2 * lead_s - 0.1)
        slots.append(sl)
        R_x[:, j] = np.sqrt((xb[sl] ** 2).mean(axis=0))
        R_a[:, j] = np.sqrt((rb[sl] ** 2).mean(axis=0))
    return slots, R_x, R_a


def analyse(rec: dict, names, fs: float, quiet_s: float, slot_s: float, lead_s: float,
            dc_gain_m_per_V: float, steps: tuple[float, float, float] | None = None,
            sensor_noise: dict | None = None) -> dict:
    """The checks of one commissioning recording (rig.runtime.recorder.read_recording's dict). steps: the valves'
    held steps after the chirps (start s, hold s, null s after each valve's pair: valve_checks), if recorded.
    sensor_noise: {kind: white noise rms per sample}, what a mount alone judges its noise floors against."""
    n = len(names)
    t = np.asarray(rec["time_s"]).ravel()
    acc = np.asarray(rec["accel_mps2"], dtype=float).reshape(len(t), -1)[:, :n]
    x = np.asarray(rec["stroke_m"], dtype=float).reshape(len(t), -1)[:, :n]
    cmd = np.asarray(rec["valve_cmd_V"], dtype=float).reshape(len(t), -1)[:, :n]
    floor = rec.get("floor_accel_mps2")
    floor = np.asarray(floor, dtype=float).reshape(len(t), -1)[:, :n] if floor is not None else None
    quiet = (t > 0.2 * quiet_s) & (t < quiet_s)
    channels = quiet_channels(acc, x, floor, quiet, fs, names, sensor_noise if n == 1 else None)
    # the table's accelerometers alone: a floor channel miswired would spoil their checks (the floor's motion is
    # no chirp's: H1 against x'' is unbiased by it); the floor is checked against them (floor_checks)
    rb, xb, cb = _band(acc, fs), _band(x, fs), _band(cmd, fs)
    w = 2 * np.pi * np.fft.rfftfreq(len(t), 1 / fs)
    xdd = np.fft.irfft(-(w ** 2)[:, None] * np.fft.rfft(xb, axis=0), n=len(t), axis=0)    # x'', exact in band
    slots, R_x, R_a = _responses(t, xb, rb, quiet_s, slot_s, lead_s)
    stroke_of, accel_of = channel_map(R_x), channel_map(R_a)     # the channel answering valve j
    mount_of = valve_map(stroke_of, accel_of)                   # the mount valve j moves (swapped CAN nodes)
    scale, gain = _scale_and_gain(names, slots, xdd, rb, cb, xb, stroke_of, accel_of, fs, dc_gain_m_per_V)
    if steps is not None:
        # the stroke over the command from the valves' held steps (DC), sign and size: the chirp's ratio at 3-6 Hz
        # lies near the actuator's corner (7.4 Hz, Eq. 9) behind the transducer's delay, and a loaded host's jitter
        # turns it (read -6.1 and +0.73 for channels ranged a decade up, which the steps put at +9.0 and +9.2)
        D = _step_matrix(t, x, cmd, steps)
        for j, m in enumerate(names):
            gain[m] = float(D[stroke_of[j], j] / dc_gain_m_per_V)
    # a transducer's unit slip (stroke_unit) scales its stroke: the valve's gain and the accelerometer's scale
    # against it are judged through its correction; a dead transducer holds no accelerometer to anything
    gain_raw, scale_raw = dict(gain), dict(scale)
    med_x = _stroke_ref(R_x, stroke_of, gain, names)
    dead_x = {m for j, m in enumerate(names) if R_x[stroke_of[j], j] < STROKE_DEAD_RATIO * med_x
              or not channels["stroke"][names[stroke_of[j]]]["alive"]}
    units = {m: 1.0 if m in dead_x else stroke_unit(gain[m], scale[m], _gain_ref(gain, m, dead_x)) for m in names}
    for m in names:                     # judged against the stroke as calibrated: its unit and sign put right
        gain[m] *= units[m]
    _against_stroke(scale, gain, units, dead_x)
    flo, floor_in = None, dict(scale)
    if floor is not None and n > 1:     # the floor checked against the table, then taken out of it (floor_pass)
        flo, scale_raw = floor_pass(names, fs, t >= t[quiet].min(), slots, rb, xdd, _band(floor, fs), cb, xb,
                                    accel_of, stroke_of, mount_of, scale, gain, units, channels, dc_gain_m_per_V,
                                    dead_x)
        scale.update(scale_raw)
        _against_stroke(scale, gain, units, dead_x)
    verdicts, findings = _verdicts(names, R_a, R_x, accel_of, stroke_of, scale, gain, channels, mount_of, med_x)
    fix = {"accel": {names[accel_of[j]]: correction(scale[m]) if SCALE_FIX[0] <= abs(scale[m]) <= SCALE_FIX[1]
                     else 1.0 for j, m in enumerate(names)},
           "stroke": {names[stroke_of[j]]: units[m] for j, m in enumerate(names)}}
    cal = _sensor_calibration(names, accel_of, stroke_of, mount_of, scale, gain, units, channels)
    named = sensor_findings(names, channels, accel_of, stroke_of, units, gain_raw, dead_x, verdicts, findings, fix,
                            null_window_m=NULL_MAX_V * abs(dc_gain_m_per_V) if steps is not None else 0.0,
                            floor_of=flo["floor_of"] if flo else None)
    if flo is not None:
        named |= floor_checks(names, flo, channels, cal, verdicts, findings, named, mount_of,
                              floor[t >= t[quiet].min()].mean(axis=0))
    faults = sensor_faults(names, accel_of, stroke_of, scale, gain, dead_x, verdicts, named)
    scale.update({m: scale_raw[m] for m in dead_x})
    _no_correction_of_refused(cal, verdicts, accel_of, stroke_of, names)
    valves = valve_checks(names, t, x, cmd, quiet, steps, stroke_of, mount_of, cal, dc_gain_m_per_V, D) \
        if steps is not None else None
    if valves is not None:
        verdicts.update(valves.pop("verdicts"))
        findings += valves.pop("findings")
        faults = sorted(faults + valves.pop("faults"), key=lambda f: (f["channel"], f["kind"]))
        cal["valve"] = valves.pop("calibration")
        valves = valves["valves"]
    return {"mounts": list(names), "channels": channels, "stroke_response_m": R_x.tolist(),
            "accel_response_mps2": R_a.tolist(), "stroke_of_valve": [names[i] for i in stroke_of],
            "accel_of_valve": [names[i] for i in accel_of], "accel_scale": scale, "valve_gain_vs_model": gain,
            "valves": valves, "verdicts": verdicts, "findings": findings, "faults": faults, "calibration": cal,
            "band_hz": list(BAND_HZ), "all_ok": all(v == "ok" for v in verdicts.values()),
            **({"floor_scale": flo["scale"], "floor_of_mount": [names[k] for k in flo["floor_of"]],
                "floor_response": flo["H"].tolist(), "accel_scale_floor_in": floor_in} if flo else {}),
            **({"notes": alone_notes(channels, floor is not None)} if n == 1 else {})}


def _stroke_ref(R_x, stroke_of, gain, names) -> float:
    """The stroke response a transducer is held against (dead below STROKE_DEAD_RATIO of it): the median over
    the valves; one mount alone has no others, so the answer a transducer reading the model's DC gain would give."""
    if len(names) == 1:
        return float(R_x[stroke_of[0], 0] / max(abs(gain[names[0]]), 1e-12))
    return float(np.median([R_x[stroke_of[j], j] for j in range(len(names))]))


def alone_notes(channels: dict, floor_fitted: bool) -> list[str]:
    """What one mount alone cannot check, in words (the report's notes)."""
    notes = ["one valve, one transducer, one accelerometer: no channel can be swapped with another (no response "
             "matrix)"]
    if not floor_fitted:
        notes.append("no floor accelerometer fitted: the floor is not checked against the table")
    for kind, rows in channels.items():
        for ch, row in rows.items():
            if row.get("held_share", 0.0) > HELD_MAX:
                notes.append(f"{kind} {ch}: noise floor not judged, {100 * row['held_share']:.0f} % of its samples "
                             f"at null repeat the one before (the host held the loop off; run again on a quieter host)")
    return notes


def _scale_and_gain(names, slots, xdd, rb, cb, xb, stroke_of, accel_of, fs, dc_gain_m_per_V) -> tuple[dict, dict]:
    """Per valve's slot: its accelerometer's scale against its stroke's x'' and its stroke over its command at the
    band's low end, over the model's DC gain."""
    scale, gain = {}, {}
    for j, m in enumerate(names):
        sl, xs, ac = slots[j], stroke_of[j], accel_of[j]
        d2 = xdd[sl, xs]
        # H1 = S(x'', a) / S(x'', x'') over the band: its size unbiased by the accelerometer's own noise and by
        # the transducer's later sample (a delay turns its phase, not its size); its sign from the real part
        nps = min(256, int(sl.sum()))
        f, pxa = signal.csd(d2, rb[sl, ac], fs=fs, nperseg=nps)
        _, pxx2 = signal.welch(d2, fs=fs, nperseg=nps)
        band = (f >= BAND_HZ[0]) & (f <= BAND_HZ[1])
        h1 = pxa[band].sum() / max(pxx2[band].sum(), 1e-300)
        scale[m] = float(abs(h1) * (1.0 if h1.real >= 0 else -1.0))
        # stroke over command at the low end of the band: the cross spectrum's ratio (the model's DC gain there)
        f, pxy = signal.csd(cb[sl, j], xb[sl, xs], fs=fs, nperseg=min(256, int(sl.sum())))
        _, pxx = signal.welch(cb[sl, j], fs=fs, nperseg=min(256, int(sl.sum())))
        low = (f >= BAND_HZ[0]) & (f <= 2 * BAND_HZ[0])
        h = pxy[low] / np.maximum(pxx[low], 1e-300)
        gain[m] = float(np.real(h.mean()) / dc_gain_m_per_V) if low.any() else math.nan
    return scale, gain


def _no_correction_of_refused(cal, verdicts, accel_of, stroke_of, names) -> None:
    """A refused or unchecked channel's measured scale is no calibration (a dead one's would multiply its noise):
    it keeps scale 1, and an unchecked one its sign."""
    for kind, of in (("accel", accel_of), ("stroke", stroke_of)):
        for j, m in enumerate(names):
            if verdicts[f"{kind}:{m}"] in ("refused", "unchecked"):
                cal[kind][names[of[j]]]["scale"] = 1.0
            if verdicts[f"{kind}:{m}"] == "unchecked":
                cal[kind][names[of[j]]]["sign"] = 1.0


def _verdicts(names, R_a, R_x, accel_of, stroke_of, scale, gain, channels, mount_of=None,
              x_ref=None) -> tuple[dict, list]:
    """Per channel ok / corrected / refused, and the findings in words (mount_of: the mount each valve moves;
    x_ref: the stroke response a transducer is held against, default the median over the valves)."""
    mount_of = list(range(len(names))) if mount_of is None else mount_of
    med_a = np.median([R_a[accel_of[j], j] / max(abs(scale[m]), 1e-12) for j, m in enumerate(names)])
    med_x = np.median([R_x[stroke_of[j], j] for j in range(len(names))]) if x_ref is None else x_ref
    verdicts, findings = {}, []
    for j, m in enumerate(names):
        ac, xs = accel_of[j], stroke_of[j]
        on = names[mount_of[j]]      # the mount the sensors answering valve j sit on (swapped nodes: not m)
        # the accelerometer answering valve j
        v = "ok"
        if R_a[ac, j] / max(abs(scale[m]), 1e-12) < DEAD_RMS_RATIO * med_a or not channels["accel"][names[ac]]["alive"]:
            v = "refused"
            findings.append(f"accelerometer of {m}: no answer to its valve (dead or unwired)")
        else:
            if ac != mount_of[j]:
                v = "corrected"
                findings.append(f"accelerometers swapped: valve {m} is answered by the channel mapped to {names[ac]}")
            s = scale[m]
            if s < 0 and abs(s) >= SCALE_FIX[0]:         # a dead channel's sign is its noise's
                v = "corrected"
                findings.append(f"accelerometer on {on}: sign inverted (scale {s:+.3f} against its stroke's x'')")
            a = abs(s)
            if abs(a - 1) > SCALE_TOL:
                if SCALE_FIX[0] <= a <= SCALE_FIX[1] and unit_slip(a):
                    v = "corrected"
                    hint = " (an input range in g read as m/s^2)" if abs(a * 9.80665 - 1) < SCALE_TOL else ""
                    findings.append(f"accelerometer on {on}: scale {a:.3f} against its stroke's x''{hint}")
                elif SCALE_FIX[0] <= a <= SCALE_FIX[1]:
                    # a wiring slip is a unit's factor; any other is a broken sensor or a measurement the host
                    # spoiled, and its inverse as a calibration made a loop unstable (57 Hz, a loaded host)
                    v = "refused"
                    findings.append(f"accelerometer on {on}: scale {a:.3f} against its stroke's x'' is no unit slip "
                                    f"(g against m/s^2, a power of ten): not corrected; commission again, then check "
                                    f"the sensor")
                else:
                    v = "refused"
                    # a range 1000 x too coarse (mm/s^2 read as m/s^2) answers as little as an unwired input: the
                    # signal lies at the module's resolution, and 1000 x its steps would be no calibration
                    dead = (" (dead, unwired, or its range 1000 x too coarse: the signal is lost below the module's "
                            "resolution; check the channel's wiring and range)") if a < SCALE_FIX[0] else ""
                    findings.append(f"accelerometer on {on}: scale {a:.3g} beyond what calibration corrects{dead}")
        verdicts[f"accel:{m}"] = v
        v = "ok"
        if R_x[xs, j] < STROKE_DEAD_RATIO * med_x:
            v = "refused"
            findings.append(f"transducer of {on}: no answer to its valve")
        elif xs != mount_of[j]:
            v = "corrected"
            findings.append(f"transducers swapped: valve {m} is answered by the channel mapped to {names[xs]}")
        if gain[m] < 0 and v != "refused":             # a dead transducer's sign is its noise's
            v = "corrected"
            findings.append(f"stroke of {on}: sign inverted against its valve (gain {gain[m]:+.2f} x the model's)")
        verdicts[f"stroke:{m}"] = v
    return verdicts, findings


def valve_map(stroke_of, accel_of) -> list[int]:
    """The mount each valve's command moves. Valve j answered by stroke channel stroke_of[j] and accelerometer
    channel accel_of[j]: when both show the same exchange, the valves' CAN nodes are swapped (one slip), not a
    transducer pair and an accelerometer pair (two). The valve map v with the fewest channels moved over the
    three maps (the valves' v, the sensors' stroke_of and accel_of after it), the identity first."""
    n = len(stroke_of)
    best, cost = list(range(n)), n + 1
    for v in itertools.permutations(range(n)):
        c = sum(v[j] != j for j in range(n)) + sum(stroke_of[j] != v[j] for j in range(n)) + \
            sum(accel_of[j] != v[j] for j in range(n))
        if c < cost:
            best, cost = list(v), c
    return best


def _cycle(perm, j: int) -> list[int]:
    """The indices of perm's cycle through j, from j."""
    out = [j]
    while perm[out[-1]] != j:
        out.append(perm[out[-1]])
    return out


def _held(t, sig, t0: float, hold_s: float):
    """The mean of sig over the settled part of a hold [t0, t0 + hold_s] (its first third left out: the
    actuator's lag corner, K_C K_L / A_p^2 of Eq. 9, and the table's slower sway settle there)."""
    sl = (t > t0 + hold_s / 3) & (t < t0 + hold_s - 0.02)
    return sig[sl].mean(axis=0)


def _step_matrix(t, x, cmd, steps) -> np.ndarray:
    """D[stroke channel i, valve j]: the stroke per volt of valve j's held steps (+A then -A, one valve after the
    other from steps = (start s, hold s, null s between))."""
    t_s, hold_s, gap_s = steps
    n = cmd.shape[1]
    D = np.zeros((x.shape[1], n))
    for j in range(n):
        t0 = t_s + j * (2 * hold_s + gap_s)
        hi, lo = _held(t, x, t0, hold_s), _held(t, x, t0 + hold_s, hold_s)
        du = _held(t, cmd[:, j], t0, hold_s) - _held(t, cmd[:, j], t0 + hold_s, hold_s)
        D[:, j] = (hi - lo) / du
    return D


def valve_checks(names, t, x, cmd, quiet, steps, stroke_of, mount_of, cal, dc_gain_m_per_V, D=None) -> dict:
    """Each valve's DC gain, null offset and node, from its held steps (+A then -A, `steps` = start, hold, null
    after) and the quiet stretch at null.

    The actuator with its load spring is a lag at DC (Eq. 9: x_p/v = G_dc / (1 + s / (K_C K_L / A_p^2))): a
    spool centred at null_V moves the stroke by -G_dc null_V and holds it there (it does not drift). So:
      D[i, j]  = d(stroke channel i) / d(command j) over the held steps  -> valve j's DC gain over the model's
      o        = the stroke channels' offsets at zero command = -D null + (the transducers' own offsets): the
                 mean over the whole recording from the quiet stretch on, less D times the commands' mean (a linear
                 system's mean answer is its DC gain times the input's mean); the quiet stretch alone (1.2 s) reads
                 the floor's slow sway of the table's twist (85 nm, 0.035 V, on the emulated rig), 15 s a quarter
    The transducers are taken to read 0 at the actuator's spring centre (their zero as installed): null = -D^-1 o,
    the table's coupling of the mounts included. A channel whose offset no null within NULL_MAX_V explains keeps
    it as its own offset (that valve's null is not judged). The stroke's calibrated offset keeps only the part
    the corrected nulls do not explain."""
    n = len(names)
    D = _step_matrix(t, x, cmd, steps) if D is None else D          # analyse measured it once already
    w = t >= t[quiet].min()
    o = x[w].mean(axis=0) - D @ cmd[w].mean(axis=0)
    own = np.array([abs(D[stroke_of[j], j]) for j in range(n)])
    # its transducer answers it: the valve can be judged (alone: against the model's, as a dead transducer is)
    # (STROKE_DEAD_RATIO: a transducer ranged a decade off answers 0.1 of the others', on the dead line's edge)
    seen = own > STROKE_DEAD_RATIO * (np.median(own) if n > 1 else abs(dc_gain_m_per_V))
    judged = [bool(seen[j] and abs(o[stroke_of[j]]) <= NULL_MAX_V * own[j]) for j in range(n)]
    null = np.full(n, math.nan)
    idx = [j for j in range(n) if judged[j]]
    if idx:                              # the judged valves' nulls from their own channels (the others unknown)
        rows_x = [stroke_of[j] for j in idx]
        null[idx] = -np.linalg.solve(D[np.ix_(rows_x, idx)], o[rows_x])
    # through the transducer's own scale; its size only: a valve's sign is no wiring fault here, the stroke's
    # sign is the transducer's (the held steps' sign holds where a chirp's ratio drowned under load)
    ks = [float(cal.get("stroke", {}).get(names[stroke_of[j]], {}).get("scale", 1.0)) for j in range(n)]
    gains = [float(abs(D[stroke_of[j], j]) * ks[j] / dc_gain_m_per_V) for j in range(n)]
    # the correction is against the valves that are ok: the table takes a share of each mount's stroke that the
    # one-actuator model has not (0.92 wired right), the same for every mount
    ok = [g for g in gains if abs(g - 1) <= GAIN_TOL]
    g_ref = float(np.median(ok)) if ok else 1.0
    verdicts, findings, faults, rows, figs = {}, [], [], {}, {}
    for j, m in enumerate(names):
        xs, g = stroke_of[j], gains[j]
        node = f"valve {m}"
        v, out = "ok", {"mount": names[mount_of[j]], "null_V": 0.0, "gain": 1.0}
        if mount_of[j] != j:
            v = "corrected"
            faults.append({"channel": f"valve:{m}", "kind": "swap"})
            if j == min(_cycle(mount_of, j)):            # one line per exchange
                findings.append("valve nodes swapped: " + ", ".join(
                    f"the command for {names[i]} moves {names[mount_of[i]]}" for i in _cycle(mount_of, j)) +
                    " (its stroke and accelerometer answer it)")
        if not seen[j]:
            v = "unchecked"
            findings.append(f"{node}: not judged (its mount's transducer does not answer it)")
        elif not GAIN_FIX[0] <= g <= GAIN_FIX[1]:
            v = "refused"
            faults.append({"channel": f"valve:{m}", "kind": "gain"})
            findings.append(f"{node}: DC gain {g:+.2f} x the model's, beyond what calibration corrects")
        elif abs(g - 1) > GAIN_TOL:
            v = "corrected" if v == "ok" else v
            faults.append({"channel": f"valve:{m}", "kind": "gain"})
            out["gain"] = g / g_ref
            findings.append(f"{node}: DC gain {g:.2f} x the model's ({g / g_ref:.2f} x the valves that are ok)")
        if judged[j] and abs(null[j]) > NULL_TOL_V:
            v = "corrected" if v == "ok" else v
            faults.append({"channel": f"valve:{m}", "kind": "null"})
            out["null_V"] = float(null[j])
            findings.append(f"{node}: null offset {null[j]:+.3f} V (its spool centres there: at zero command the "
                            f"stroke sits {-D[xs, j] * null[j] * ks[j] * 1e6:+.2f} um off)")
        verdicts[f"valve:{m}"] = v
        rows[m] = out
        figs[m] = {"dc_gain_vs_model": g, "null_V": float(null[j]) if judged[j] else None,
                   "moves": names[mount_of[j]], "stroke_per_V_m": D[:, j].tolist()}
    # the strokes' offsets: o over the whole recording (the quiet stretch's own mean reads the twist's sway, and
    # a calibration taking that off leaves it as an apparent null in the next commissioning), less the part the
    # corrected nulls make: the transducer's own offset is what is left
    left = o + D @ np.array([rows[m]["null_V"] for m in names])        # (a valve not judged: 0, as it was)
    for i, ch in enumerate(names):
        if "offset_m" in cal.get("stroke", {}).get(ch, {}):
            cal["stroke"][ch]["offset_m"] = float(left[i])
    return {"verdicts": verdicts, "findings": findings, "faults": faults, "calibration": rows, "valves": figs}


def text(res: dict) -> str:
    """The report in words: one line per channel, then the findings."""
    lines = []
    where = "in the held steps" if res.get("valves") else f"at {BAND_HZ[0]:g}-{2 * BAND_HZ[0]:g} Hz"
    for m in res["mounts"]:
        a, s = res["verdicts"][f"accel:{m}"], res["verdicts"][f"stroke:{m}"]
        ch = res["channels"]
        lines.append(f"{m}: accelerometer {a} (scale {res['accel_scale'][m]:+.3f} against x'', noise "
                     f"{ch['accel'][m]['noise_rms_mps2'] * 1e3:.2f} mm/s^2 rms, offset "
                     f"{ch['accel'][m]['offset_mps2'] * 1e3:+.2f} mm/s^2); transducer {s} (stroke/command {where} "
                     f"{res['valve_gain_vs_model'][m]:+.2f} x the model's DC gain, noise "
                     f"{ch['stroke'][m]['noise_rms_m'] * 1e9:.1f} nm rms)")
    for m, k in zip(res["mounts"], res.get("floor_of_mount") or ()):
        f = res["channels"]["floor"][k]
        lines.append(f"{m}: floor accelerometer {res['verdicts'][f'floor:{m}']} (channel mapped to {k}, scale "
                     f"{res['floor_scale'][m]:+.3f} against the table less its stroke's x'', noise "
                     f"{f['noise_rms_mps2'] * 1e3:.2f} mm/s^2 rms, offset {f['offset_mps2'] * 1e3:+.2f} mm/s^2)")
    for m, v in (res.get("valves") or {}).items():
        null = "not judged (its transducer's own offset)" if v["null_V"] is None else f"{v['null_V']:+.3f} V"
        lines.append(f"{m}: valve {res['verdicts'][f'valve:{m}']} (DC gain {v['dc_gain_vs_model']:.2f} x the model's, "
                     f"null {null}, moves {v['moves']})")
    lines += [f"  ({note})" for note in res.get("notes", ())]
    lines += [f"  {f}" for f in res["findings"]] or ["  every channel ok"]
    return "\n".join(lines)


def calibration_toml(res: dict, source: str) -> str:
    """commissioning.toml: per channel its mount, sign, scale and offset (the channel map)."""
    out = [f"# rig commission: calibration from {source}", ""]
    for kind, rows in res["calibration"].items():
        for ch, row in rows.items():
            out.append(f"[{kind}.{ch}]")
            out += [f"{k} = {v!r}" if isinstance(v, str) else f"{k} = {v:.6g}" for k, v in row.items()]
            out.append("")
    return "\n".join(out).replace("'", '"')


def plot(res: dict, rec: dict, mount: str, path) -> None:
    """One mount's PNG: its valve's response in every stroke and accelerometer channel (the channel map)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = res["mounts"]
    j = names.index(mount)
    floor = res.get("floor_response")
    fig, ax = plt.subplots(1, 3 if floor else 2, figsize=(13.5 if floor else 9, 3.5))
    ax[0].bar(names, [r[j] * 1e6 for r in res["stroke_response_m"]])
    ax[0].set_title(f"valve {mount}: stroke response (um rms, {BAND_HZ[0]:g}-{BAND_HZ[1]:g} Hz)")
    ax[1].bar(names, [r[j] for r in res["accel_response_mps2"]])
    ax[1].set_title(f"accelerometer response (m/s^2 rms); scale {res['accel_scale'][mount]:+.3f}")
    if floor:                # each floor channel against the floor under this mount (the table less its x'')
        ax[2].bar(names, [r[j] for r in floor])
        ax[2].axhline(1.0, color="k", lw=0.5)
        ax[2].set_title(f"floor channels against the floor under {mount}; scale {res['floor_scale'][mount]:+.3f}")
    for a in ax:
        a.tick_params(axis="x", labelrotation=30)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_alone(res: dict, rec: dict, path, quiet_s: float, lead_s: float, steps) -> None:
    """One mount alone (no response matrix to draw): its polarity, the accelerometer against its stroke's x''
    (BAND_HZ, half a second of its chirp), and its valve's held steps, stroke and command."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    m = res["mounts"][0]
    t = np.asarray(rec["time_s"]).ravel()
    fs = 1.0 / float(np.median(np.diff(t)))
    a = np.asarray(rec["accel_mps2"], dtype=float).reshape(len(t), -1)[:, 0]
    x = np.asarray(rec["stroke_m"], dtype=float).reshape(len(t), -1)[:, 0]
    u = np.asarray(rec["valve_cmd_V"], dtype=float).reshape(len(t), -1)[:, 0]
    w = 2 * np.pi * np.fft.rfftfreq(len(t), 1 / fs)
    xdd = np.fft.irfft(-(w ** 2) * np.fft.rfft(_band(x, fs)), n=len(t))
    t0 = quiet_s + lead_s + 0.5
    sl = (t > t0) & (t < t0 + 0.5)
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.5))
    ax[0].plot(t[sl], xdd[sl], label="x'' of the stroke")
    ax[0].plot(t[sl], _band(a, fs)[sl], label="accelerometer", alpha=0.8)
    ax[0].set_title(f"{m}: polarity, {BAND_HZ[0]:g}-{BAND_HZ[1]:g} Hz (scale {res['accel_scale'][m]:+.3f})")
    ax[0].set_xlabel("time (s)")
    ax[0].set_ylabel("m/s^2")
    ax[0].legend(fontsize=8)
    hs = (t > steps[0] - 0.1) & (t < steps[0] + 2 * steps[1] + steps[2])
    ax[1].plot(t[hs], x[hs] * 1e6, label="stroke (um)")
    ax[1].plot(t[hs], u[hs], label="command (V)")
    v = (res.get("valves") or {}).get(m, {})
    null = "not judged" if v.get("null_V") is None else f"null {v['null_V']:+.3f} V"
    ax[1].set_title(f"valve: DC gain {v.get('dc_gain_vs_model', float('nan')):.2f} x model's, {null}")
    ax[1].set_xlabel("time (s)")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
