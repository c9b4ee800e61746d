"""User-facing errors.

Every problem a user can cause (a missing file, a malformed value, a simulation that blows up) is raised as a
:class:`CausalGSError` whose message is one line naming the file or the value. The command line prints that line and
exits non-zero without a traceback; library callers catch the class.
"""


class CausalGSError(Exception):
    """An error caused by the input, explained in one line."""


class DataError(CausalGSError):
    """A dataset, image, camera or checkpoint file is missing or malformed."""


class RuntimeConfigError(CausalGSError):
    """The compute runtime (Taichi/torch) cannot be set up as asked."""
