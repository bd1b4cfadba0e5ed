"""Recordings: what a run or another lab's file holds, read into one typed Recording.

  recording.py   the Recording and the rules every recording passes (validated, mend_gaps, check_plausible)
  files.py       the one reader of files: format detection, gzip, CSV and text, .mat v5 and v7.3, HDF5
  rigformat.py   rig's own formats (time_s, valve_cmd_V, position_m, accel_mps2): the loader and the writers
  signalmap.py   a plant file's [signals]: another lab's file read as it is, in SI units; load_recording_for,
                 what the commands call
  closedloop.py  was the recording made in closed loop (the command computed from the measurement)?
  command.py     what the recorded command is (sweep, multisine, steps, noise): read from the command itself
  samples.py     the samples as a fit takes them (finite, plausible, not constant), their command and loop
  runfile.py     a run of the four-mount rig (rig run --record, rig hil; docs/RUN_RECORDING.md): its four mounts'
                 channels, the floor's when measured, the isolation modes
"""
