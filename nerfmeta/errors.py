"""User-facing errors.

Anything a user can cause (a bad file, a bad value) raises :class:`NerfmetaError` with one line
that names the file or value and says what to do. The CLI prints that line on stderr and exits
with code 2; programming errors keep their tracebacks.
"""


class NerfmetaError(Exception):
    """A problem with the user's input, reported as one line without a traceback."""


class SceneError(NerfmetaError):
    """A scene folder or file cannot be read as a scene."""


class ConfigError(NerfmetaError):
    """A value given on the command line or in a config is not allowed."""
