"""Where a session's bytes go: the file is created safely and cut back cleanly when the disk fails.

Creating (``create_session_file``):

* The directory is opened once and the file is named relative to it (``dir_fd``). Under a
  confining ``base_dir`` (``perfcap serve``'s sessions directory, where every paired phone may
  name a file) each directory on the way is opened with ``O_DIRECTORY | O_NOFOLLOW``, so a
  directory swapped for a symbolic link between a check and the open cannot lead outside: there is
  no check-then-open, only opens that refuse links. ``..``, hidden names (a leading ``.``), NUL
  bytes and names not ending in ``.mcap`` are refused there.
* The session is first written under a hidden temporary name (``.NAME.<random>.part``, created with
  ``O_CREAT | O_EXCL | O_NOFOLLOW``) and put in place with ``link`` (which fails if the name exists:
  creation stays exclusive) once its MCAP header and session metadata are on disk. A recorder
  killed while starting therefore leaves nothing under the name, never an empty file that blocks
  the next take. The temporary file is locked (``flock``) while its writer lives; a later take to
  the same name removes the ones whose writer is gone.
* ``overwrite`` replaces only a perfcap session (MCAP magic and a header with profile ``perfcap``)
  or an empty file, atomically (``rename`` over it); any other file, a link or a directory is
  refused.

Writing (``SessionFile``): the MCAP writer's bytes are buffered and written at each ``flush``;
``commit`` marks what is on disk as complete (the recorder commits at each flush, at an MCAP record
boundary). When a write or fsync fails (disk full, file size limit, I/O error), the file is cut
back to the last commit, so it ends on a complete record and holds exactly what was committed.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import secrets
import stat
import struct
from dataclasses import dataclass

from capture.errors import ConfigError, SessionError, SessionExistsError

MCAP_MAGIC = b"\x89MCAP0\r\n"
SESSION_PROFILE = "perfcap"
#: a session name given under a confining directory must end so
SESSION_SUFFIX = ".mcap"
#: bytes buffered before they are written even without a flush
WRITE_BUFFER_BYTES = 1 << 20

_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_CLOEXEC", 0)
_NOFOLLOW = os.O_NOFOLLOW
_CREATE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
_PROBE_FLAGS = os.O_RDONLY | _NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
_hdr = struct.Struct("<BQ")


def _strerror(exc: OSError) -> str:
    return exc.strerror or str(exc)


# -- what is at a name --------------------------------------------------------------------------------
def describe_existing(dir_fd: int, name: str) -> tuple[str, bool]:
    """What the entry ``name`` in ``dir_fd`` is, in words, and whether ``overwrite`` may replace it
    (a perfcap session or an empty regular file). Links are not followed."""
    try:
        st = os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except FileNotFoundError:
        return "nothing", True
    except OSError as exc:
        raise SessionError(f"cannot create {name}: {_strerror(exc)}", path=name) from None
    if stat.S_ISLNK(st.st_mode):
        return "a symbolic link (never replaced: sessions are not written through links)", False
    if stat.S_ISDIR(st.st_mode):
        return "a directory, not a session file", False
    if not stat.S_ISREG(st.st_mode):
        return "not a regular file (never replaced)", False
    if st.st_size == 0:
        return "an empty file (perhaps an earlier take killed while it started)", True
    try:
        fd = os.open(name, _PROBE_FLAGS, dir_fd=dir_fd)
    except OSError as exc:
        return f"a file that cannot be read ({_strerror(exc)}; never replaced)", False
    try:
        head = os.pread(fd, 512, 0)
        tail = os.pread(fd, len(MCAP_MAGIC), max(0, st.st_size - len(MCAP_MAGIC)))
    except OSError as exc:
        return f"a file that cannot be read ({_strerror(exc)}; never replaced)", False
    finally:
        os.close(fd)
    if not is_session_header(head):
        return "not a perfcap session (never replaced, even with overwrite)", False
    if tail != MCAP_MAGIC or st.st_size < 2 * len(MCAP_MAGIC):
        return "a perfcap session cut short (no MCAP footer: an earlier take was killed or its disk failed)", True
    return "a perfcap session", True


def is_session_header(head: bytes) -> bool:
    """``head`` (the first bytes of a file) starts with the MCAP magic and a header record whose
    profile is perfcap's."""
    o = len(MCAP_MAGIC)
    if head[:o] != MCAP_MAGIC or len(head) < o + _hdr.size + 4:
        return False
    opcode, _length = _hdr.unpack_from(head, o)
    if opcode != 0x01:
        return False
    (n,) = struct.unpack_from("<I", head, o + _hdr.size)
    start = o + _hdr.size + 4
    return head[start:start + n] == SESSION_PROFILE.encode() and n == len(SESSION_PROFILE)


# -- where a name leads --------------------------------------------------------------------------------
@dataclass
class SessionTarget:
    """An open directory and a name in it: where a session will be created."""

    dir_fd: int
    name: str
    #: the path as shown to people (under ``base_dir`` when confined)
    path: str

    def close(self) -> None:
        if self.dir_fd >= 0:
            os.close(self.dir_fd)
            self.dir_fd = -1


def _check_component(part: str, given: str, confined: bool) -> None:
    if part == "..":
        raise ConfigError(f"{given!r}: '..' is not allowed; give a name inside the sessions directory")
    if confined and part.startswith("."):
        raise ConfigError(f"{given!r}: names starting with '.' are not used for sessions")
    if len(part.encode("utf-8", "surrogateescape")) > 255:
        raise ConfigError(f"{given!r}: a name in it is longer than 255 bytes")


def resolve_target(path: str, base_dir: str | None = None) -> SessionTarget:
    """Open the directory ``path`` is to be created in and return it with the file's name.

    Args:
        path: the session file; with ``base_dir``, relative to it (or absolute inside it).
        base_dir: confine ``path`` to this directory: every directory below it is opened without
            following links, and ``..``, hidden names and names not ending in ``.mcap`` are refused.

    Raises:
        ConfigError: the path is empty, malformed, leaves ``base_dir``, or a directory on the way is
            missing, a link or not a directory.
    """
    if not isinstance(path, str):
        raise ConfigError(f"the session path must be a string, not {type(path).__name__}")
    if path == "":
        raise ConfigError("the session path is empty; give a file name such as take1.mcap")
    if "\0" in path:
        raise ConfigError(f"{path!r}: a session path cannot contain a NUL byte")
    if len(path) > 4096:
        raise ConfigError("the session path is longer than 4096 characters")
    if path.endswith(("/", os.sep)):
        raise ConfigError(f"{path!r} names a directory; give a file name such as take1.mcap")
    if base_dir is None:
        head, name = os.path.split(path)
        _check_component(name, path, False)
        if name in ("", "."):
            raise ConfigError(f"{path!r} names a directory; give a file name such as take1.mcap")
        try:
            dfd = os.open(head or ".", _DIR_FLAGS)
        except OSError as exc:
            raise ConfigError(f"cannot create {path}: directory {head or '.'}: {_strerror(exc)}") from None
        return SessionTarget(dfd, name, path)
    base_real = os.path.realpath(base_dir)
    if os.path.isabs(path):
        norm = os.path.normpath(path)
        rel = None
        for b in (os.path.abspath(base_dir), base_real):
            if norm == b:
                raise ConfigError(f"{path!r} is the sessions directory itself; give a file name in it")
            if norm.startswith(b.rstrip(os.sep) + os.sep):
                rel = norm[len(b.rstrip(os.sep)) + 1:]
                break
        if rel is None or ".." in path.split(os.sep):
            raise ConfigError(f"{path!r} is outside the sessions directory {base_real}; give a name inside it")
    else:
        rel = path
    parts = [p for p in rel.split(os.sep) if p not in ("", ".")]
    for p in parts:
        _check_component(p, path, True)
    if not parts:
        raise ConfigError(f"{path!r} names the sessions directory; give a file name such as take1.mcap")
    if not parts[-1].endswith(SESSION_SUFFIX) or parts[-1] == SESSION_SUFFIX:
        raise ConfigError(f"{path!r}: session names end in {SESSION_SUFFIX} (e.g. take1.mcap)")
    try:
        dfd = os.open(base_real, _DIR_FLAGS)
    except OSError as exc:
        raise ConfigError(f"the sessions directory {base_real} cannot be opened: {_strerror(exc)}") from None
    try:
        for i, p in enumerate(parts[:-1]):
            try:
                nfd = os.open(p, _DIR_FLAGS | _NOFOLLOW, dir_fd=dfd)
            except OSError as exc:
                where = os.path.join(*parts[:i + 1])
                if exc.errno in (errno.ELOOP, errno.ENOTDIR, errno.EMLINK):
                    raise ConfigError(f"{path!r}: {where} is a symbolic link or not a directory; sessions are"
                                      f" written only inside the sessions directory {base_real}") from None
                if exc.errno == errno.ENOENT:
                    raise ConfigError(f"{path!r}: there is no directory {where} in the sessions directory"
                                      f" {base_real} (create it first)") from None
                raise ConfigError(f"{path!r}: directory {where}: {_strerror(exc)}") from None
            os.close(dfd)
            dfd = nfd
    except BaseException:
        os.close(dfd)
        raise
    return SessionTarget(dfd, parts[-1], os.path.join(base_real, *parts))


# -- the file ---------------------------------------------------------------------------------------
class SessionFile:
    """The session's file as the MCAP writer sees it (``write``, ``tell``, ``flush``), buffered here,
    cut back to the last ``commit`` when the disk fails (see the module docstring).

    Args:
        fd: the open file (positioned at 0, empty).
        path: for messages.
    """

    def __init__(self, fd: int, path: str) -> None:
        self.fd = fd
        self.path = path
        self._buf = bytearray()
        self._written = 0       # bytes handed to the OS
        self.committed = 0      # bytes known complete on disk
        self.error: OSError | None = None
        #: after a failure: the file was cut back to ``committed`` (False: it may hold more)
        self.cut_back = False

    # the parts of a binary file the mcap writer uses
    def write(self, data: bytes | bytearray | memoryview) -> int:
        self._check()
        self._buf += data
        if len(self._buf) >= WRITE_BUFFER_BYTES:
            self._drain()
        return len(data)

    def tell(self) -> int:
        return self._written + len(self._buf)

    def flush(self) -> None:
        self._check()
        self._drain()

    def _check(self) -> None:
        if self.error is not None:
            raise self.error
        if self.fd < 0:
            raise ValueError("write to a closed session file")

    def _drain(self) -> None:
        view = memoryview(self._buf)
        done = 0
        try:
            while done < len(view):
                n = os.write(self.fd, view[done:])
                done += n
                self._written += n
        except OSError as exc:
            view.release()
            self._fail(exc)
            raise
        view.release()
        del self._buf[:]

    def sync(self) -> None:
        """``fsync`` the file (a failure is handled as a failed write)."""
        self._check()
        try:
            os.fsync(self.fd)
        except OSError as exc:
            self._fail(exc)
            raise

    def commit(self) -> None:
        """Everything written so far is complete (call after ``flush`` and, if wanted, ``sync``)."""
        if self.error is None and not self._buf:
            self.committed = self._written

    def _fail(self, exc: OSError) -> None:
        if self.error is not None:
            return
        self.error = exc
        self._buf = bytearray()
        try:
            os.ftruncate(self.fd, self.committed)
            self.cut_back = True
        except OSError:
            self.cut_back = False

    def abort(self) -> None:
        """Stop writing after a failure not seen here (an exception in the writer): cut back to the
        last commit and close."""
        if self.error is None:
            self._fail(OSError(errno.ECANCELED, "recording stopped"))
        self.close()

    def close(self) -> None:
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.close(self.fd)
            self.fd = -1


def _remove_stale_parts(dir_fd: int, name: str) -> None:
    """Remove ``.NAME.*.part`` files whose writer is gone (nobody holds their lock)."""
    prefix = f".{name}."
    try:
        entries = os.listdir(dir_fd)
    except OSError:
        return
    for e in entries:
        if not (e.startswith(prefix) and e.endswith(".part")):
            continue
        try:
            fd = os.open(e, _PROBE_FLAGS, dir_fd=dir_fd)
        except OSError:
            continue
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # its writer is alive
            with contextlib.suppress(OSError):
                os.unlink(e, dir_fd=dir_fd)
        finally:
            os.close(fd)


class PendingSession:
    """A session being created: written under a temporary name until ``publish`` puts it in place.

    Raises (constructor):
        SessionExistsError: something is at the name and ``overwrite`` is false, or it is not a file
            ``overwrite`` may replace.
        SessionError: the file cannot be created.
    """

    def __init__(self, target: SessionTarget, overwrite: bool) -> None:
        self.target = target
        self.overwrite = overwrite
        self.path = target.path
        self._check_existing()
        _remove_stale_parts(target.dir_fd, target.name)
        self.tmp_name = ""
        fd = -1
        for _ in range(8):
            self.tmp_name = f".{target.name}.{secrets.token_hex(4)}.part"
            try:
                fd = os.open(self.tmp_name, _CREATE_FLAGS, 0o666, dir_fd=target.dir_fd)
                break
            except FileExistsError:
                continue
            except OSError as exc:
                raise SessionError(f"cannot create {self.path}: {_strerror(exc)}", path=self.path) from exc
        if fd < 0:
            raise SessionError(f"cannot create {self.path}: no free temporary name", path=self.path)
        with contextlib.suppress(OSError):
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self.file = SessionFile(fd, self.path)
        self.published = False

    def _check_existing(self) -> None:
        what, replaceable = describe_existing(self.target.dir_fd, self.target.name)
        if what == "nothing":
            return
        if not replaceable:
            raise SessionExistsError(f"{self.path} exists and is {what}", path=self.path)
        if not self.overwrite:
            raise SessionExistsError(f"{self.path} already exists (use --overwrite to replace it; it is {what})",
                                     path=self.path)

    def publish(self) -> None:
        """Put the file (its header on disk) in place under its name.

        Raises:
            SessionExistsError: the name was taken meanwhile (without ``overwrite``), or by a file
                ``overwrite`` may not replace.
            SessionError: the file cannot be put in place.
        """
        d, tmp, name = self.target.dir_fd, self.tmp_name, self.target.name
        try:
            if self.overwrite:
                self._check_existing()
                os.rename(tmp, name, src_dir_fd=d, dst_dir_fd=d)
            else:
                try:
                    os.link(tmp, name, src_dir_fd=d, dst_dir_fd=d, follow_symlinks=False)
                except FileExistsError:
                    raise SessionExistsError(f"{self.path} already exists (created meanwhile; use --overwrite to"
                                             " replace it)", path=self.path) from None
                except OSError as exc:
                    if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EMLINK):
                        raise
                    # no hard links on this file system: take the name exclusively, then move over it
                    fd = os.open(name, _CREATE_FLAGS, 0o666, dir_fd=d)
                    os.close(fd)
                    os.rename(tmp, name, src_dir_fd=d, dst_dir_fd=d)
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(tmp, dir_fd=d)
        except SessionError:
            raise
        except FileExistsError:
            raise SessionExistsError(f"{self.path} already exists (use --overwrite to replace it)",
                                     path=self.path) from None
        except OSError as exc:
            raise SessionError(f"cannot create {self.path}: {_strerror(exc)}", path=self.path) from exc
        self.published = True
        self.target.close()

    def discard(self) -> None:
        """Give up before ``publish``: the temporary file is removed."""
        self.file.close()
        if not self.published and self.target.dir_fd >= 0:
            with contextlib.suppress(OSError):
                os.unlink(self.tmp_name, dir_fd=self.target.dir_fd)
        self.target.close()
