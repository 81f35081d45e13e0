"""One orchestrator per database file: an advisory lock (``fcntl.flock``) on ``DB.lock`` beside
it, holding the owner's pid, taken for the orchestrator process's life.

Two orchestrators on one SQLite file would each schedule the same campaigns' episodes and
record them twice; the second one must refuse to start and say who holds the file.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path


class DatabaseInUse(RuntimeError):
    """Another process holds the database's lock; the message names the file and its pid."""


class DatabaseFolderError(RuntimeError):
    """The database's folder does not exist and cannot be created (the message says what to do)."""


def make_folder(db_path: str | os.PathLike) -> Path:
    """Create the folder of ``db_path`` if it is missing and return it.

    Raises
    ------
    DatabaseFolderError
        It cannot be created (one line naming the folder and the cause).
    """
    folder = Path(db_path).expanduser().resolve().parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        if not folder.is_dir():
            raise DatabaseFolderError(f"cannot create the database folder {folder}: {(err.strerror or str(err)).lower()}; "
                                      "create it, or give --db a path you can write") from None
    return folder


def lock_path(db_path: str | os.PathLike) -> Path:
    return Path(f"{os.fspath(db_path)}.lock")


class DatabaseLock:
    """An exclusive lock on ``db_path``; ``acquire()`` raises ``DatabaseInUse`` if it is held."""

    def __init__(self, db_path: str | os.PathLike) -> None:
        self.db_path = os.fspath(db_path)
        self.path = lock_path(db_path)
        self._fd: int | None = None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> "DatabaseLock":
        """Take the lock (nothing to do if this object holds it already).

        Raises
        ------
        DatabaseInUse
            Another process holds it.
        OSError
            The lock file cannot be created or opened (e.g. a read-only file system).
        """
        if self._fd is not None:
            return self
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_pid(fd)
            os.close(fd)
            who = f" (pid {holder})" if holder else ""
            raise DatabaseInUse(f"the database {self.db_path} is in use by another orchestrator{who}: "
                                "stop it, or give this one another database") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases the flock
            self._fd = None

    def __enter__(self) -> "DatabaseLock":
        return self.acquire()

    def __exit__(self, *_exc) -> None:
        self.release()


def holder(db_path: str | os.PathLike) -> int | None:
    """The pid holding ``db_path``'s lock (0 if unknown), or None when it is free (or there is
    no lock file)."""
    path = lock_path(db_path)
    try:
        fd = os.open(path, os.O_RDONLY)  # read-only: works on a read-only file system too (flock needs no write access)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read_pid(fd) or 0
        return None  # closing the descriptor releases the lock we just took
    finally:
        os.close(fd)


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode().strip()
        return int(text) if text else None
    except (OSError, ValueError):
        return None
