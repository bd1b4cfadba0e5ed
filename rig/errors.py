"""User-facing errors: one clear line, no traceback (the CLI prints str(err) and exits non-zero)."""


class RigError(Exception):
    """A problem the user can fix: bad file, bad config value, device not answering."""


class ConfigError(RigError):
    """Invalid configuration: the message names the file and the key."""


class RecordingError(RigError):
    """A recording that cannot be read: the message names the file and the problem."""


class DeviceError(RigError):
    """A device that does not answer or reports a fault: the message names the device."""


EXIT_HARM = 3          # a command's exit status when the do-no-harm supervisor switched isolation off
