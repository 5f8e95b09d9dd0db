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


def message_line(err: BaseException, *, last: bool = False, limit: int | None = None) -> str:
    """One line of a library's exception for a one-line error: the first line of its message (``last``: the last,
    where a tool puts its reason last, as ffmpeg does), cut to ``limit`` characters; its type name for an empty one."""
    lines = str(err).strip().splitlines()
    line = (lines[-1] if last else lines[0]) if lines else type(err).__name__
    return line if limit is None else line[:limit]
