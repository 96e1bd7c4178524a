"""The errors a user can cause, each with a message that is the whole story: a command prints
it on one line and exits 1 (`gst_jax.cli.run`), a library caller reads it."""


class DataError(ValueError):
    """A data file or request that cannot be used; the message says where and why."""


class RunError(Exception):
    """A work directory or model name that cannot be used; the message says why."""


class NonFiniteError(RuntimeError):
    """A single run's step had a non-finite loss or gradient; the last checkpoint is kept."""


class DeviceError(ValueError):
    """Devices asked for that this machine or these processes do not have."""


class Interrupted(KeyboardInterrupt):
    """A stop signal (Ctrl-C, SIGTERM) ended the work at a safe point; the message says what
    was saved and what rerunning the command does."""


USER_ERRORS = (DataError, RunError, NonFiniteError, DeviceError)
