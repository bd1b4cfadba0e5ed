"""The operator console: a live web page for `rig run --console` (see rig/console/link.py for what runs where).

  live.py      the loop's rows in shared memory (the loop writes, the web server reads)
  protocol.py  the commands and the control socket's messages
  link.py      the loop's side: the web server's start, the publication, the commands into the session
  feed.py      the web server's side: rows -> traces, timing, spectra, VC curves
  server.py    the web server (Starlette on uvicorn) and its page (static/, uPlot vendored with its licence)
  runner.py    `rig run --console`: the run, and the chirp identification the page can ask for
  bench.py     `rig bench loop --console`: the loop's timing with a browser attached against without
"""
