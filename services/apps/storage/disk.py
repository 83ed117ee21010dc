"""The blocking filesystem side of a storage service: every call stays inside one directory.

:class:`Folder` reaches a file by opening each directory on its way relative
to the one before (``openat`` with ``O_NOFOLLOW``), never by joining path
text: a symbolic link planted anywhere on the way (or as the file itself) is
refused, so nothing outside the directory is ever read or written, whatever
the disk holds. Names are checked by :mod:`services.apps.storage.names` first.

A write is atomic: a temporary file in the same directory, written in full,
``fsync``-ed, renamed over the name, and the directory ``fsync``-ed. A reader
sees the old content or the new, never half of either, and a crash leaves no
half-written file under the name.

Every method blocks (``fsync`` takes milliseconds); the service runs them on
its worker threads, never on the event loop. OS errors become PropertyErrors
(:func:`os_error`): a full disk is RESOURCE_EXHAUSTED, a name the filesystem
cannot hold INVALID_ARGUMENT.
"""

from __future__ import annotations

import errno
import os
import secrets
import stat
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

from services.apps.storage.names import MAX_DEPTH, TEMP_PREFIX, check_name, is_carried
from services.kernel.errors import (
    FailedPrecondition,
    InvalidArgument,
    NotFound,
    PropertyError,
    ResourceExhausted,
    Unavailable,
)

__all__ = ["FileInfo", "Folder", "os_error"]

_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
#: O_NONBLOCK: opening a FIFO planted under a name must not hang a worker; it is refused as not a file.
_READ_FLAGS = os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK
_WRITE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
_CHUNK = 1024 * 1024


@dataclass(frozen=True, slots=True)
class FileInfo:
    """One regular file under the directory."""

    name: str
    size: int
    #: Modification time, nanoseconds since the epoch.
    mtime_ns: int


def os_error(exc: OSError, what: str) -> PropertyError:
    """The PropertyError for ``exc`` met while doing ``what`` (``store `a.txt```)."""
    code = exc.errno
    reason = exc.strerror or str(exc)
    if code in (errno.ENOSPC, errno.EDQUOT):
        return ResourceExhausted(f"{what}: the disk is full ({reason}); nothing was changed")
    if code == errno.EFBIG:
        return ResourceExhausted(f"{what}: the file is too large for the filesystem ({reason})")
    if code == errno.ENOENT:
        return NotFound(f"{what}: no such file")
    if code in (errno.ENAMETOOLONG, errno.EILSEQ, errno.EINVAL):
        return InvalidArgument(f"{what}: the filesystem cannot hold this name ({reason})")
    if code in (errno.ELOOP, errno.EMLINK):
        return FailedPrecondition(f"{what}: a symbolic link is on the way; storage never follows links")
    if code == errno.ENOTDIR:
        return FailedPrecondition(f"{what}: a part of the name is a file, not a directory")
    if code == errno.EISDIR:
        return FailedPrecondition(f"{what}: it is a directory, not a file")
    if code in (errno.EACCES, errno.EPERM):
        return FailedPrecondition(f"{what}: the gateway may not do this on disk ({reason})")
    if code == errno.EROFS:
        return FailedPrecondition(f"{what}: the filesystem is read-only")
    return PropertyError(f"{what}: {reason}")


class Folder:
    """One directory, reached only through its own file descriptors; see the module docstring."""

    def __init__(self, root: Path) -> None:
        self.root = root

    # -- reaching a file ---------------------------------------------------

    def _open_root(self) -> int:
        try:
            return os.open(self.root, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        except OSError as exc:
            # Not the file's fault: the directory itself is gone (or was replaced by a file).
            raise Unavailable(
                f"the storage directory {str(self.root)!r} cannot be opened: {exc.strerror or exc}"
            ) from None

    @contextmanager
    def _parent(self, name: str, what: str, *, create: bool = False) -> Iterator[tuple[int, str]]:
        """The open directory holding ``name`` and the last segment; directories made when ``create``.

        An OSError, met here or in the ``with`` block, comes out as the PropertyError that says
        what went wrong while doing ``what`` (:func:`os_error`)."""
        try:
            *dirs, leaf = name.split("/")
            fd = self._open_root()
            try:
                for segment in dirs:
                    try:
                        child = os.open(segment, _DIR_FLAGS, dir_fd=fd)
                    except OSError as exc:
                        if exc.errno in (errno.ENOTDIR, errno.ELOOP):
                            _refuse_on_the_way(segment, fd, what)
                        if exc.errno != errno.ENOENT or not create:
                            raise
                        try:
                            os.mkdir(segment, 0o777, dir_fd=fd)
                        except FileExistsError:
                            pass  # made by someone else meanwhile
                        else:
                            os.fsync(fd)
                        child = os.open(segment, _DIR_FLAGS, dir_fd=fd)
                    os.close(fd)
                    fd = child
                yield fd, leaf
            finally:
                os.close(fd)
        except OSError as exc:
            raise os_error(exc, what) from None

    @staticmethod
    def _lstat(leaf: str, fd: int) -> os.stat_result | None:
        try:
            return os.stat(leaf, dir_fd=fd, follow_symlinks=False)
        except FileNotFoundError:
            return None

    @staticmethod
    def _refuse_odd(st: os.stat_result, what: str) -> None:
        if stat.S_ISLNK(st.st_mode):
            raise FailedPrecondition(f"{what}: it is a symbolic link; storage never follows links")
        if stat.S_ISDIR(st.st_mode):
            raise FailedPrecondition(f"{what}: it is a directory, not a file")
        if not stat.S_ISREG(st.st_mode):
            raise FailedPrecondition(f"{what}: it is not a regular file")

    @classmethod
    def _existing_file(cls, leaf: str, fd: int, what: str) -> os.stat_result:
        """The status of regular file ``leaf``; NotFound when there is none, FailedPrecondition
        when it is something else."""
        st = cls._lstat(leaf, fd)
        if st is None:
            raise NotFound(f"{what}: no such file")
        cls._refuse_odd(st, what)
        return st

    # -- the operations ------------------------------------------------------

    def read(self, name: str, limit: int) -> bytes:
        """The bytes of file ``name``; NotFound, or ResourceExhausted when it holds more than ``limit``."""
        what = f"read `{check_name(name)}`"
        with self._parent(name, what) as (dir_fd, leaf):
            try:
                fd = os.open(leaf, _READ_FLAGS, dir_fd=dir_fd)
            except OSError as exc:
                st = self._lstat(leaf, dir_fd)
                if st is not None:
                    self._refuse_odd(st, what)
                raise exc
            try:
                st = os.fstat(fd)
                self._refuse_odd(st, what)
                if st.st_size > limit:
                    raise _too_big(what, st.st_size, limit)
                chunks: list[bytes] = []
                total = 0
                while True:
                    chunk = os.read(fd, min(_CHUNK, limit + 1 - total))
                    if not chunk:
                        break
                    chunks.append(chunk)
                    total += len(chunk)
                    if total > limit:  # it grew while read (written in place by someone else)
                        raise _too_big(what, total, limit)
                return b"".join(chunks)
            finally:
                os.close(fd)

    def write(self, name: str, data: bytes) -> None:
        """Store ``data`` as file ``name`` atomically, making its directories; see the module docstring."""
        what = f"store `{check_name(name)}`"
        with self._parent(name, what, create=True) as (dir_fd, leaf):
            old = self._lstat(leaf, dir_fd)
            if old is not None:
                self._refuse_odd(old, what)
            temp = TEMP_PREFIX + secrets.token_hex(8)
            fd = os.open(temp, _WRITE_FLAGS, 0o666, dir_fd=dir_fd)
            try:
                try:
                    if old is not None:
                        os.fchmod(fd, stat.S_IMODE(old.st_mode))
                    view = memoryview(data)
                    while view:
                        view = view[os.write(fd, view) :]
                    os.fsync(fd)
                finally:
                    os.close(fd)
                os.rename(temp, leaf, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)
            except BaseException:
                _unlink_quietly(temp, dir_fd)
                raise
            os.fsync(dir_fd)

    def remove(self, name: str) -> None:
        """Remove file ``name``; NotFound when there is none."""
        what = f"remove `{check_name(name)}`"
        with self._parent(name, what) as (dir_fd, leaf):
            self._existing_file(leaf, dir_fd, what)
            os.unlink(leaf, dir_fd=dir_fd)
            os.fsync(dir_fd)

    def info(self, name: str) -> FileInfo:
        """Size and modification time of file ``name``; NotFound when there is none."""
        what = f"info of `{check_name(name)}`"
        with self._parent(name, what) as (dir_fd, leaf):
            st = self._existing_file(leaf, dir_fd, what)
            return FileInfo(name, st.st_size, st.st_mtime_ns)

    def scan(self, keep: Callable[[FileInfo], bool], limit: int) -> tuple[list[FileInfo], bool]:
        """Every regular file below the directory that ``keep`` keeps, sorted by name, at most ``limit``.

        Symbolic links, temporary files and names the service cannot carry are
        skipped; so are directories deeper than the name grammar reaches. The
        flag is True when the walk stopped at ``limit`` files (then the list
        holds the first ones found, not the first by name).
        """
        found: list[FileInfo] = []
        truncated = False
        fd = self._open_root()
        stack: list[tuple[int, str, int]] = [(fd, "", 1)]
        try:
            while stack and not truncated:
                dir_fd, prefix, depth = stack.pop()
                try:
                    with os.scandir(dir_fd) as entries:
                        for entry in entries:
                            name = prefix + entry.name
                            if entry.name.startswith(TEMP_PREFIX):
                                continue
                            if entry.is_dir(follow_symlinks=False):
                                if depth < MAX_DEPTH and is_carried(name):
                                    try:
                                        child = os.open(entry.name, _DIR_FLAGS, dir_fd=dir_fd)
                                    except OSError:
                                        continue  # gone meanwhile, or not ours to read
                                    stack.append((child, name + "/", depth + 1))
                                continue
                            if not entry.is_file(follow_symlinks=False) or not is_carried(name):
                                continue
                            try:
                                st = entry.stat(follow_symlinks=False)
                            except OSError:
                                continue  # removed meanwhile
                            info = FileInfo(name, st.st_size, st.st_mtime_ns)
                            if not keep(info):
                                continue
                            if len(found) >= limit:
                                truncated = True
                                break
                            found.append(info)
                except OSError:
                    pass  # a directory removed or closed to us meanwhile: its files are gone
                finally:
                    os.close(dir_fd)
        finally:
            for dir_fd, _, _ in stack:
                os.close(dir_fd)
        found.sort(key=lambda f: f.name)
        return found, truncated


def _refuse_on_the_way(segment: str, dir_fd: int, what: str) -> None:
    """Say why directory ``segment`` could not be opened: a link, or a file."""
    try:
        st = os.stat(segment, dir_fd=dir_fd, follow_symlinks=False)
    except OSError:
        return
    if stat.S_ISLNK(st.st_mode):
        raise FailedPrecondition(f"{what}: `{segment}` is a symbolic link; storage never follows links")
    raise FailedPrecondition(f"{what}: `{segment}` is a file, not a directory")


def _too_big(what: str, size: int, limit: int) -> ResourceExhausted:
    return ResourceExhausted(
        f"{what}: the file is {size} bytes, over the limit of {limit} bytes (max_file_size); its `info` works"
    )


def _unlink_quietly(name: str, dir_fd: int) -> None:
    with suppress(OSError):
        os.unlink(name, dir_fd=dir_fd)
