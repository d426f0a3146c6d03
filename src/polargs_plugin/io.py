"""File helpers shared by every module: atomic writes, input errors that name the file, writability
checks and folder locks.

Files written through :func:`atomic_path` / :func:`atomic_write` appear complete or not at all and
get the mode an ordinary ``open()`` would give them (``0o666`` less the process umask), not the
``0o600`` of the temporary file they are written as.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import socket
import tempfile
import time
from pathlib import Path
from typing import IO, Any, Iterator

__all__ = [
    "PolarInputError",
    "atomic_write",
    "atomic_path",
    "remove_stale_temporaries",
    "remove_stale_temporaries_in",
    "atomic_torch_save",
    "torch_error_line",
    "current_umask",
    "check_writable",
    "FolderLock",
    "FolderLockedError",
    "json_safe",
    "write_json",
]


class PolarInputError(ValueError):
    """Bad input: the message always names the offending file (or folder) and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def current_umask() -> int:
    """The process umask, read without changing it where the system allows (Linux /proc)."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # elsewhere: set and restore (not thread-safe, but brief)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    For writers that take a file name (cv2.imwrite, np.save, open3d). The temporary name keeps
    the suffix so that format detection by extension still works. Nothing is left behind on error.
    The file gets mode ``0o666 & ~umask`` (mkstemp creates it ``0o600``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():  # a writer may have replaced the file; give it the ordinary mode
            os.chmod(tmp_path, 0o666 & ~current_umask())
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files :func:`atomic_path` left beside ``path`` when its writer was
    killed (SIGKILL, a power cut) before renaming them; returns those removed.

    Only for a caller that alone writes ``path`` now (e.g. under the folder's :class:`FolderLock`):
    another writer's temporary file in progress would go too.
    """
    path = Path(path)
    return _remove_temporaries(path.parent, re.escape(path.stem), path.suffix)


def remove_stale_temporaries_in(folder: str | os.PathLike, suffix: str) -> list[Path]:
    """:func:`remove_stale_temporaries` for every file of ``folder`` whose name ends in ``suffix``
    (a cache of many entries, e.g. ``.pt``), under the same condition: the caller alone writes
    the folder now."""
    return _remove_temporaries(Path(folder), r"[^/]+", suffix)


def _remove_temporaries(folder: Path, stem: str, suffix: str) -> list[Path]:
    # mkstemp's names: the prefix ".<stem>.", 8 characters of [a-z0-9_], the suffix
    name = re.compile(rf"\.{stem}\.[a-z0-9_]{{8}}{re.escape(suffix)}")
    removed = []
    with contextlib.suppress(OSError):
        for candidate in folder.iterdir():
            if name.fullmatch(candidate.name) and candidate.is_file():
                with contextlib.suppress(FileNotFoundError):
                    candidate.unlink()
                    removed.append(candidate)
    return removed


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w") -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; rename onto ``path`` on success."""
    with atomic_path(path) as tmp:
        with open(tmp, mode) as handle:
            yield handle


def atomic_torch_save(data: Any, path: str | os.PathLike) -> Path:
    """``torch.save(data, path)`` through :func:`atomic_path`: the file is complete or absent.

    torch's file writer reports a failed write (a full disk, a file size limit) as RuntimeError
    (``[enforce fail at inline_container.cc] . unexpected pos ...``); it is raised here as
    OSError naming ``path``, like any other failed write.
    """
    import torch

    path = Path(path)
    with atomic_path(path) as tmp:
        try:
            torch.save(data, tmp)
        except RuntimeError as err:
            raise OSError(errno.EIO, f"cannot write the file (torch: {torch_error_line(err)}; is the disk full?)",
                          str(path)) from None
    return path


def torch_error_line(err: BaseException) -> str:
    """The first sentence of a torch error's text, without the C++ source location that starts
    it (``[enforce fail at inline_container.cc:672] .``)."""
    lines = str(err).strip().splitlines()
    first = re.sub(r"^\[enforce fail at [^\]]*\]\s*\.?\s*", "", lines[0]) if lines else ""
    return re.split(r"(?<=\w)\. ", first)[0] or type(err).__name__


def json_safe(value: Any) -> Any:
    """``value`` as strict JSON can hold it: NaN and infinities become None (null), tuples lists,
    keys strings; dicts and lists are converted all the way down.

    >>> json_safe({"a": float("nan"), 1: (2.0, float("inf"))})
    {'a': None, '1': [2.0, None]}
    """
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented strict JSON (:func:`json_safe`), atomically."""
    with atomic_write(path) as handle:
        json.dump(json_safe(data), handle, indent=2, allow_nan=False)
    return Path(path)


def check_writable(folder: str | os.PathLike) -> Path:
    """Create ``folder`` (and its parents) if needed and prove that files can be written in it.

    A test file is created and removed, so a read-only mount, a full disk or missing permissions
    are found before any long computation, not after it.

    Returns:
        ``folder`` as a Path.

    Raises:
        PolarInputError: naming the folder (or the file in its way) and the reason.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise PolarInputError(folder, "exists and is not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".polargs-write-test-", dir=folder)
        try:
            os.write(fd, b"polargs")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as err:
        raise PolarInputError(folder, f"cannot write there ({err.strerror or type(err).__name__})") from None
    return folder


class FolderLockedError(PolarInputError):
    """The folder is locked by a live process; ``holder`` is the lock file's content."""

    def __init__(self, path: str | os.PathLike, problem: str, holder: dict[str, Any]):
        super().__init__(path, problem)
        self.holder = holder


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    except OSError:
        return True
    return True


# Tries to take a lock: each ends with a lock, an error, or a lock that changed hands meanwhile.
_LOCK_ATTEMPTS = 20


class FolderLock:
    """An exclusive lock on a folder: a lock file holding the holder's pid, host and start time.

    The file is created atomically, complete with its content (written beside it, then
    hard-linked, which fails when a lock exists); :meth:`release` removes it if it is still ours.
    A lock left by a process that no longer runs on this host (killed with SIGKILL, a power cut)
    is *stale*: it is taken over and :attr:`note` says so; of several processes taking over the
    same stale lock at once exactly one gets it (the others find its live lock). A lock of a live
    process, or of another host (whose processes cannot be checked), raises
    :class:`FolderLockedError` naming the holder.

    Usage::

        with FolderLock(run_dir / "train.lock", command="polargs train ..."):
            ...
    """

    def __init__(self, path: str | os.PathLike, command: str = ""):
        self.path = Path(path)
        self.command = command
        self.note: str | None = None
        self._content: dict[str, Any] | None = None

    @property
    def held(self) -> bool:
        """Whether this object holds the lock (acquired and not yet released)."""
        return self._content is not None

    def describe(self, holder: dict[str, Any]) -> str:
        started = holder.get("started")
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started)) if isinstance(started, (int, float)) else "?"
        text = f"pid {holder.get('pid', '?')} on host {holder.get('host', '?')} since {when}"
        if holder.get("command"):
            text += f" ({holder['command']})"
        return text

    def _read(self) -> dict[str, Any] | None:
        try:
            data = json.loads(self.path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return {}
        return data if isinstance(data, dict) else {}

    def acquire(self) -> "FolderLock":
        content = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.time(), "command": self.command}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        for attempt in range(_LOCK_ATTEMPTS):
            if self._create(content):
                self._content = content
                return self
            seen = self._signature()
            holder = self._read()
            if holder is None:
                continue  # released meanwhile: try again
            self._check_stale(holder)
            if self._take_over(seen, holder):
                self.note = f"{self.path}: took over the stale lock of {self.describe(holder)}, which no longer runs"
            else:
                time.sleep(0.002 * (attempt + 1))  # another process is taking it over: see who won
        raise PolarInputError(self.path, "could not take the lock (it keeps changing hands)")

    def _create(self, content: dict[str, Any]) -> bool:
        """Create the lock file complete with ``content``; False when a lock exists."""
        fd, tmp = tempfile.mkstemp(prefix=".lock-", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as handle:
                json.dump(content, handle)
            os.chmod(tmp, 0o666 & ~current_umask())
            try:
                os.link(tmp, self.path)  # atomic; fails if the lock exists
                return True
            except FileExistsError:
                return False
            except OSError:  # no hard links on this file system: O_EXCL create
                try:
                    excl = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
                except FileExistsError:
                    return False
                with os.fdopen(excl, "w") as handle:
                    json.dump(content, handle)
                return True
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)

    def _signature(self) -> tuple[int, int, int] | None:
        """(inode, mtime in ns, size) of the lock file, None when there is none."""
        try:
            stat = self.path.stat()
        except OSError:
            return None
        return stat.st_ino, stat.st_mtime_ns, stat.st_size

    def _check_stale(self, holder: dict[str, Any]) -> None:
        """Raise FolderLockedError unless ``holder``'s lock is stale: its process no longer runs
        on this host, or the file is unreadable and older than a minute (a writer is not that slow)."""
        if not holder:
            stale = False
            with contextlib.suppress(OSError):
                stale = time.time() - self.path.stat().st_mtime > 60
            if not stale:
                raise FolderLockedError(self.path, "locked (unreadable lock file); delete it if no polargs command uses the folder", holder)
            return
        if holder.get("host") == socket.gethostname() and isinstance(holder.get("pid"), int) and not _pid_alive(holder["pid"]):
            return
        raise FolderLockedError(
            self.path,
            f"the folder is in use by {self.describe(holder)}; wait for it to finish, or delete "
            "this lock file if that process is gone",
            holder,
        )

    def _take_over(self, seen: tuple[int, int, int] | None, holder: dict[str, Any]) -> bool:
        """Remove the stale lock file judged by its ``seen`` signature and ``holder`` content, if
        this process is the one to do it; False when another process is taking it over.

        Deleting what was read moments ago could delete the lock another process has taken over
        since; so the remover first creates ``<lock>.takeover`` exclusively (one process at a
        time), and removes the lock only if it is still the stale one. A claim older than a
        minute was left by a process killed while holding it, and is removed.
        """
        claim = self.path.with_name(self.path.name + ".takeover")
        try:
            os.close(os.open(claim, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        except FileExistsError:
            with contextlib.suppress(OSError):
                if time.time() - claim.stat().st_mtime > 60:
                    os.unlink(claim)
            return False
        try:
            if seen is None or self._signature() != seen or self._read() != holder:
                return False  # taken over (or released) since it was judged
            os.unlink(self.path)
            return True
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(claim)

    def release(self) -> None:
        """Remove the lock file if it still holds this process's lock."""
        if self._content is None:
            return
        holder = self._read()
        if holder is not None and holder.get("pid") == self._content["pid"] and holder.get("started") == self._content["started"]:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)
        self._content = None

    def __enter__(self) -> "FolderLock":
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
