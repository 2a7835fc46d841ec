"""Reading inputs and writing results safely: one place for every file edgecal reads or writes.

Writes are atomic (a reader sees the old file or the new one, never half of one), durable (the file and
its folder are fsynced around the rename), created with the process umask's permissions (0644 under
umask 022, like any other tool's output: a service reading a rig copied to /etc must be able to) and
never clobber an earlier result unless asked (``force``). A set of files (rig.yaml and its camera_info
files) is written all-or-nothing as far as a file system allows: every temporary first, then every rename.

Temporaries are unnamed (Linux ``O_TMPFILE``) wherever the file system allows, so a writer killed
mid-write leaves nothing behind; a temporary gets a name only for the two system calls that move it onto
an existing file, or on a file system without ``O_TMPFILE``. Named temporaries look like
``.NAME.PID-XXXXXXXX.edgecal-tmp``; a process's first write into a folder removes those whose writer is gone.

Reads go through :func:`read_input`, which names the file and says "permission denied" when that is
the reason (not "unreadable"): the usual mistake when a service user reads a file copied by root.
"""

from __future__ import annotations

import errno
import os
import re
import secrets
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from edgecal.errors import InputError

# the file names of write_atomic_set: str, Path or both (a Mapping's key type is invariant)
_PathT = TypeVar("_PathT", bound="str | Path")

TEMP_SUFFIX = ".edgecal-tmp"
# .NAME.PID-XXXXXXXX.edgecal-tmp: the PID tells a stale temporary (its writer is gone) from a live one.
_TEMP_NAME = re.compile(r"^\..+\.(?P<pid>\d+)-[0-9a-f]{8}" + re.escape(TEMP_SUFFIX) + r"$")
_PROC_FD = "/proc/self/fd"
# Folders swept for stale temporaries by this process already (a recording writes thousands of
# frames into one folder: one listing per folder and process is enough).
_swept: set[str] = set()


def _user() -> str:
    try:
        import pwd
        return pwd.getpwuid(os.geteuid()).pw_name
    except (ImportError, KeyError):
        return f"uid {os.geteuid()}"


def permission_denied(path: str | Path, what: str) -> InputError:
    """The one message for a file this process may not read or write."""
    return InputError(f"{path}: permission denied (the {what} is not accessible to user {_user()}; "
                      "check the file's and its folders' permissions)")


def read_input(path: str | Path, what: str = "file", max_bytes: int | None = None) -> bytes:
    """The bytes of an input file; InputError naming the file (and "permission denied" when that is why).

    ``what`` names the kind of file in messages ("image", "calibration file", ...); ``max_bytes``
    refuses files too big to be what they claim (read at most that many bytes plus one).
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            data = fh.read() if max_bytes is None else fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise InputError(f"{p}: {what} not found (check the path)") from None
    except PermissionError:
        raise permission_denied(p, what) from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a folder, not a file") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read the {what} ({exc.strerror or exc})") from None
    if max_bytes is not None and len(data) > max_bytes:
        raise InputError(f"{p}: more than {max_bytes / (1 << 20):g} MB, too big for a {what}")
    return data


def refuse_existing(paths: Iterable[Path], force: bool) -> None:
    """InputError for the first path that already exists, unless ``force``."""
    if force:
        return
    for p in paths:
        if Path(p).exists():
            raise InputError(f"{p}: already exists; choose another output path or pass --force to overwrite")


def _writable_folder(folder: Path, create: bool) -> None:
    """InputError unless ``folder`` is (or, with ``create``, can be made as) a folder this process writes into."""
    probe = folder
    while create and not probe.exists() and probe != probe.parent:
        probe = probe.parent  # the first existing ancestor is where the new folders would be made
    if not probe.exists():
        raise InputError(f"{folder}: the folder does not exist (create it first)")
    if not probe.is_dir():
        raise InputError(f"{folder}: cannot write here, {probe} is a file, not a folder")
    if not os.access(probe, os.W_OK | os.X_OK, effective_ids=os.access in os.supports_effective_ids):
        raise InputError(f"{folder}: permission denied (user {_user()} cannot write into {probe}; "
                         "choose another output path or fix the folder's permissions)")


def make_folders(folder: str | Path) -> Path:
    """Create ``folder`` and its parents if missing; InputError naming it when the system refuses (a read-only
    or virtual file system such as /proc, no space, a file in the way)."""
    f = Path(folder)
    try:
        f.mkdir(parents=True, exist_ok=True)
    except PermissionError:
        raise permission_denied(f, "output folder") from None
    except OSError as exc:
        raise InputError(f"{f}: cannot create the folder ({exc.strerror or type(exc).__name__}); "
                         "choose another output path") from None
    return f


def check_outputs(paths: Iterable[str | Path], force: bool, create_folders: bool = False) -> None:
    """Refuse, before any work is done, outputs that could not be written or would clobber a file.

    Each path's folder must exist (or, with ``create_folders``, be creatable) and be writable by this
    process; an existing file is refused unless ``force``, an existing folder always.
    """
    for p in (Path(x) for x in paths):
        _writable_folder(p.parent, create_folders)
        if p.is_dir():
            raise InputError(f"{p}: is a folder; choose a file name")
        if p.exists() and not force:
            raise InputError(f"{p}: the file exists; pass --force to replace it")


def remove_stale_temps(folder: str | Path) -> list[Path]:
    """Remove the named temporaries in ``folder`` whose writing process no longer runs; return them."""
    removed: list[Path] = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        m = _TEMP_NAME.match(name)
        if m is None or _process_alive(int(m.group("pid"))):
            continue
        try:
            os.unlink(os.path.join(folder, name))
            removed.append(Path(folder) / name)
        except OSError:
            pass
    return removed


def supports_unnamed_temporaries(folder: str | Path) -> bool:
    """Whether files written into ``folder`` start unnamed (O_TMPFILE and /proc), so a kill leaves nothing."""
    if not os.path.isdir(_PROC_FD):
        return False
    try:
        os.close(os.open(folder, os.O_TMPFILE | os.O_WRONLY | os.O_CLOEXEC, 0o600))
    except OSError:
        return False
    return True


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


class _Temp:
    """One file being written: an open descriptor in the destination folder, unnamed when possible."""

    def __init__(self, path: Path, dir_fd: int) -> None:
        self.path = path
        self.dir_fd = dir_fd
        self.name: str | None = None  # set while the temporary has a name in the folder
        self.fd = -1
        if os.path.isdir(_PROC_FD):  # an unnamed file can only be given a name through /proc/self/fd
            try:
                self.fd = os.open(path.parent, os.O_TMPFILE | os.O_WRONLY | os.O_CLOEXEC, 0o666)
            except OSError as exc:
                if exc.errno not in (errno.EOPNOTSUPP, errno.EISDIR, errno.EINVAL):
                    raise
        if self.fd < 0:
            self.name = self._fresh_name()
            # 0o666 and the umask decide the permissions, as for any other program's output
            self.fd = os.open(self.name, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666,
                              dir_fd=dir_fd)

    def _fresh_name(self) -> str:
        return f".{self.path.name}.{os.getpid()}-{secrets.token_hex(4)}{TEMP_SUFFIX}"

    def write(self, data: bytes, durable: bool) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.fd, view):]
        if durable:
            os.fsync(self.fd)

    def name_for_replace(self) -> None:
        """Give an unnamed temporary a name if its destination exists (link cannot replace a file)."""
        if self.name is None and os.path.lexists(self.path):
            name = self._fresh_name()
            os.link(f"{_PROC_FD}/{self.fd}", name, dst_dir_fd=self.dir_fd, follow_symlinks=True)
            self.name = name

    def commit(self) -> None:
        """Move the temporary onto its destination (one link or one rename, both atomic)."""
        if self.name is None:
            try:
                os.link(f"{_PROC_FD}/{self.fd}", self.path.name, dst_dir_fd=self.dir_fd, follow_symlinks=True)
                return
            except FileExistsError:  # created meanwhile by someone else: replace it like any other
                self.name_for_replace()
        assert self.name is not None  # name_for_replace set it
        os.replace(self.name, self.path.name, src_dir_fd=self.dir_fd, dst_dir_fd=self.dir_fd)
        self.name = None

    def discard(self) -> None:
        """Forget the temporary (an unnamed one vanishes with its descriptor)."""
        if self.name is not None:
            try:
                os.unlink(self.name, dir_fd=self.dir_fd)
            except OSError:
                pass
            self.name = None
        self.close()

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def write_atomic_set(files: Mapping[_PathT, bytes], durable: bool = True) -> None:
    """Write several files as one set: every file's temporary is written (and fsynced) before any is renamed.

    A crash before the renames leaves all the old files; the renames themselves take microseconds.
    Folders are created if missing. ``durable=False`` skips the fsyncs (see :func:`sync_paths`).
    """
    temps: list[_Temp] = []
    dir_fds: dict[Path, int] = {}
    try:
        for raw, data in files.items():
            path = Path(raw)
            folder = path.parent
            if folder not in dir_fds:
                make_folders(folder)
                dir_fds[folder] = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
                key = str(folder.resolve())
                if key not in _swept:
                    _swept.add(key)
                    remove_stale_temps(folder)
            temps.append(_Temp(path, dir_fds[folder]))
            temps[-1].write(data, durable)
        for t in temps:
            t.name_for_replace()
        for t in temps:
            t.commit()
        if durable:
            for fd in dir_fds.values():
                os.fsync(fd)  # the renames themselves reach the disk
    except PermissionError as exc:
        raise permission_denied(exc.filename or next(iter(files)), "output folder") from None
    except OSError as exc:  # no space left, a read-only file system, a file where a folder should be ...
        raise InputError(f"{exc.filename or next(iter(files))}: cannot write ({exc.strerror or exc})") from None
    finally:
        for t in temps:
            t.discard()
        for fd in dir_fds.values():
            os.close(fd)


def write_atomic(path: str | Path, data: bytes, durable: bool = True) -> None:
    """Write ``data`` to ``path`` atomically, with the umask's permissions (see the module docstring)."""
    write_atomic_set({path: data}, durable=durable)


def sync_paths(paths: Iterable[str | Path]) -> None:
    """fsync files written with ``durable=False`` and then their folders (batched durability)."""
    folders: set[Path] = set()
    for p in (Path(x) for x in paths):
        fd = os.open(p, os.O_RDONLY | os.O_CLOEXEC)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        folders.add(p.parent)
    for folder in folders:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def png_bytes(image: np.ndarray, compression: int = 1) -> bytes:
    """Lossless PNG encoding; level 1 is several times faster than the default and ~10 % bigger."""
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)])
    if not ok:
        raise InputError(f"could not encode an image of shape {image.shape} and type {image.dtype} as PNG")
    return buf.tobytes()


def write_png(path: str | Path, image: np.ndarray, force: bool = False) -> None:
    """Encode ``image`` as PNG and write it atomically (refusing to replace a file unless ``force``)."""
    refuse_existing([Path(path)], force)
    write_atomic(path, png_bytes(image))
