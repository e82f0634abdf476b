"""Files given as input (cell files, secret files, bags) are regular files.

A named pipe, a device or a socket named as a cell file, a token or users file or a bag would
block its reader in ``open`` or ``read`` (a FIFO nobody writes to: forever) or stream without end
(``/dev/zero``): :func:`open_regular` opens without blocking, refuses anything but a regular file
with an :class:`OSError` whose ``strerror`` says what it is, and returns the file for reading.
"""

from __future__ import annotations

import errno
import os
import stat
from typing import BinaryIO

_KINDS = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def kind_of(mode: int) -> str:
    """What a file of ``mode`` is, in words ('' for a regular file)."""
    if stat.S_ISREG(mode):
        return ""
    return next((text for test, text in _KINDS if test(mode)), "not a regular file")


def not_regular(path: str | os.PathLike[str], mode: int) -> OSError:
    return OSError(errno.EINVAL, f"not a regular file: {kind_of(mode)}", str(path))


def open_regular(path: str | os.PathLike[str]) -> BinaryIO:
    """``path`` opened for reading in binary, if it is a regular file (else :class:`OSError`;
    a FIFO is neither opened for long nor read)."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise not_regular(path, mode)
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
