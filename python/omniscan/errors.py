"""The exceptions omniscan raises. Each message is the library's: it names
the file and the problem, as the command line prints it."""


class OmniscanError(Exception):
    """Any error from omniscan."""


class InputError(OmniscanError, ValueError):
    """A file or setting omniscan cannot use: a capture that does not
    validate, a malformed model, a value out of range."""


class FileError(OmniscanError, OSError):
    """A file could not be read or written: missing, a permission, a full
    disk."""


class OutputInUse(OmniscanError):
    """Another omniscan process is writing the same output (its lock is
    held); the message names the process."""
