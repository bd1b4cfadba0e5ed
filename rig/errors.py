"""User-facing errors: one clear line, no traceback (the CLI prints str(err) and exits non-zero)."""


class RigError(Exception):
    """A problem the user can fix: bad file, bad config value, device not answering."""


class ConfigError(RigError):
    """Invalid configuration: the message names the file and the key."""


class RecordingError(RigError):
    """A recording that cannot be read: the message names the file and the problem."""


class DeviceError(RigError):
    """A device that does not answer or reports a fault: the message names the device."""


class FaultError(RigError):
    """The safety rules stopped a run (valves at null): the message says which rule and when. Exit EXIT_FAULT."""


# The commands' exit statuses (README "Exit statuses"), one table for all of them.
EXIT_FAULT = 1         # the safety rules stopped the run
EXIT_INPUT = 2         # bad input, or refused at start: nothing was run
EXIT_HARM = 3          # isolation made the table worse: do-no-harm switched it off, or a mode metered worse than off
EXIT_FINDINGS = 4      # rig commission: a channel needs the calibration file or is refused
EXIT_SUSPECT = 5       # finished and wrote its results, but they fall short as said in a warning line: the host
                       # did not keep time, the recording has gaps, or the model fits poorly
EXIT_INTERRUPTED = 130   # Ctrl-C (128 + SIGINT) outside a run that stops on it safely
EXIT_TERMINATED = 143    # SIGTERM (128 + SIGTERM, as the shell shows a process it ended) outside such a run
EXIT_STOPPED_BY = {"SIGINT": EXIT_INTERRUPTED, "SIGTERM": EXIT_TERMINATED}   # a run's stop reason -> its exit
