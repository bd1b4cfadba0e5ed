"""The runtime: what runs a rig, period by period (docs/ARCHITECTURE.md shows how the parts fit).

  session    builds a run from a config and a backend name and tears it down (the commands are thin over it)
  loop       one period: read -> kernel -> write -> record; puts the parts below together
  scheduler  absolute deadlines, overrun policy, timing, the gap/lag/missed-deadline rules, the start-up check
  gate       the lifecycle gate: requests from other threads applied at a period boundary, faults, safe stop
  kernel     the compiled period over its memory block (checks, controllers, limits, the recording row)
  layout     the recording row's channels and column offsets
  safety     the compiled sensor checks, command limits and oscillation rule; the watchdog thread
  tap        the kernel's row into the recorder's ring
  ring       the producer's rule of a shared row ring (the recorder's, the console's live ring)
  recorder   the recording ring and its writer process (HDF5)
  lifecycle  the lifecycle states and transitions
  clock      the real and the simulated clock
  rt         real-time set-up of the loop's thread and the helpers' priorities
  libc       the C library as the process has it (clock_nanosleep, futex, mlockall)
  lock       one process per rig: a lock per device
  inject     fault rehearsal: a backend's knobs at a loop time
  signals    signals held before a session exists
"""
