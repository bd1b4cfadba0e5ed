"""Batches: one analysis (rig diagnose, rig identify) done to many recordings, on a local process pool or a Dask
cluster, each recording in its own output folder, with a summary of them all and their trends.

  inputs.py   which recordings a batch is given (files, folders, globs), each one's folder name and date
  rows.py     one recording's summary row, made from the analysis's typed results
  run.py      the batch: resumes what was done, a failure is one row, the summary current after each
  pool.py     where the work runs: local processes, or Dask futures on a cluster given its scheduler
  summary.py  summary.csv, summary.md and summary.json
  trends.py   how each parameter and named effect's size moves over the recordings' dates, and what changed
  command.py  the command line's part shared by the commands that take a batch
"""
