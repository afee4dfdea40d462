"""Output transactions: every file of one case appears together, complete, or not at all.

An :class:`OutputTransaction` stages each output as a temporary file in the output's own
folder; :meth:`~OutputTransaction.commit` renames them all onto their destinations at the end,
and any failure (an exception, Ctrl-C, SIGTERM) removes every staged file and leaves earlier
outputs exactly as they were. :func:`atomic_path` is the one-file case that every single writer
uses.

Temporary names carry the writer's host and process id,
``.<name>.<host>-<pid>-<token>.part<ext>``, so a later run can tell the leftovers of a run that
was killed (``kill -9``, a power cut) from files another run is writing right now: leftovers
whose process is gone (same host) or that are older than :data:`STALE_SECONDS` (any host) are
removed by :func:`remove_stale` whenever a transaction stages into that folder.

New files get mode 0666 minus the process umask (as ``open()`` would), so the final files have
the usual permissions (0644 under umask 022). Every operating-system failure becomes an
:class:`~BoneWatertightLib.errors.OutputError` naming the output (exit code 5).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import secrets
import socket
import time
from typing import Callable, List, Optional, Union

from ..errors import InputError, OutputError

PathLike = Union[str, os.PathLike]

# Permission bits requested for a new output file; the kernel removes the umask's bits.
NEW_FILE_MODE = 0o666

# A temporary file older than this is a leftover whatever host wrote it: staging one case's
# outputs takes seconds to minutes.
STALE_SECONDS = 24 * 3600.0

# Fallback maximum length of one file name (bytes) where the file system does not say.
DEFAULT_NAME_MAX = 255

_HOST = hashlib.sha1(socket.gethostname().encode("utf-8", "replace")).hexdigest()[:6]
_TEMP_RE = re.compile(r"^\.(?P<base>.*)\.(?P<host>[0-9a-f]{6})-(?P<pid>\d+)-[0-9a-f]{8}"
                      r"\.(?P<kind>part|prev)(?P<ext>\.[^.]+(\.[^.]+)?)?$")
# Temporary names of earlier versions (no host or pid, the extensions they wrote): removed
# only by age.
_OLD_TEMP_RE = re.compile(r"^\..+\.[0-9a-f]{8}\.part\.(stl|ply|vtp|vtk|obj|json|png|nrrd|csv|md"
                          r"|txt)$")


# ----------------------------------------------------------------------------------------
# signals during a commit

_critical_depth = 0
_pending_signal: Optional[int] = None


@contextlib.contextmanager
def critical_section():
    """Defer cancellation by :func:`defer_signal`-aware handlers while the block runs.

    The commit of a transaction (a few renames) runs inside one, so a SIGTERM that arrives
    half-way neither leaves half the files renamed nor interrupts the roll-back. The signal is
    acted on as soon as the block ends (the handler is called again then).
    """
    global _critical_depth, _pending_signal
    _critical_depth += 1
    try:
        yield
    finally:
        _critical_depth -= 1
        if _critical_depth == 0 and _pending_signal is not None:
            signum, _pending_signal = _pending_signal, None
            import signal

            handler = signal.getsignal(signum)
            if callable(handler):
                handler(signum, None)


def defer_signal(signum: int) -> bool:
    """For signal handlers: True (and remember ``signum``) inside a critical section."""
    global _pending_signal
    if _critical_depth > 0:
        _pending_signal = signum
        return True
    return False


# ----------------------------------------------------------------------------------------
# temporary names and stale leftovers

def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine still runs (another user's process counts)."""
    if pid <= 0:
        return False
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's process
        return True
    except OSError:
        return True
    return True


def list_names(folder: PathLike) -> List[str]:
    """The names in ``folder``; none when it cannot be listed (housekeeping ignores that)."""
    try:
        return os.listdir(os.fspath(folder))
    except OSError:
        return []


def is_temporary_name(name: str) -> bool:
    """True for the name of a staged (or backup) file of a transaction, of any version."""
    return bool(_TEMP_RE.match(name) or _OLD_TEMP_RE.match(name))


def remove_stale(folder: PathLike, now: Optional[float] = None) -> List[str]:
    """Remove the temporary files that killed runs left in ``folder``; return their paths.

    A temporary file is a leftover when the process that wrote it is gone (same host), or when
    it is older than :data:`STALE_SECONDS` (any host; also the names of older versions). Files
    of runs still alive are never touched. Errors (a folder that cannot be listed, a file
    removed meanwhile) are ignored: this is housekeeping.
    """
    folder = os.fspath(folder)
    now = time.time() if now is None else now
    removed = []
    for name in list_names(folder):
        if not name.startswith("."):
            continue
        match = _TEMP_RE.match(name)
        if match is None and not _OLD_TEMP_RE.match(name):
            continue
        path = os.path.join(folder, name)
        try:
            age = now - os.lstat(path).st_mtime
        except OSError:
            continue
        dead = (match is not None and match.group("host") == _HOST
                and not pid_alive(int(match.group("pid"))))
        if dead or age > STALE_SECONDS:
            try:
                os.remove(path)
                removed.append(path)
            except OSError:
                pass
    return removed


def _name_max(folder: str) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):
        return DEFAULT_NAME_MAX


def _temp_name(base: str, ext: str, kind: str, name_max: int) -> str:
    tag = f".{_HOST}-{os.getpid()}-{secrets.token_hex(4)}.{kind}{ext}"
    room = name_max - len(tag.encode()) - 1
    short = base.encode()[:max(room, 0)].decode("utf-8", "ignore")
    return f".{short}{tag}"


def _reason(exc: BaseException) -> str:
    """The operating system's words for an OSError ('No space left on device')."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return " ".join(str(exc).split()) or type(exc).__name__


def output_error(path: str, exc: BaseException, what: str = "write",
                 temporary: Optional[str] = None) -> OutputError:
    """An OutputError naming ``path``, the reason and what to do.

    ``temporary``: a staged file's name that the reason may mention; it is replaced by
    ``path`` (users never see the temporary names).
    """
    reason = _reason(exc)
    if temporary:
        reason = reason.replace(temporary, path)
    code = getattr(exc, "errno", None)
    advice = {
        errno.ENOSPC: "free some space or choose another folder",
        errno.EDQUOT: "free some space or choose another folder",
        errno.EFBIG: "the file is larger than this process may write; raise the file-size "
                     "limit (ulimit -f) or choose another folder",
        errno.EACCES: "choose a folder you can write to",
        errno.EPERM: "choose a folder you can write to",
        errno.EROFS: "the file system is read-only; choose another folder",
        errno.ENAMETOOLONG: "choose a shorter name",
        errno.EISDIR: "give a file name, not a folder",
        errno.ENOTDIR: "a part of the path is a file, not a folder",
    }.get(code, "check the path and the disk")
    return OutputError(f"Cannot {what} {path}: {reason}; {advice}.")


# ----------------------------------------------------------------------------------------
# the transaction

class OutputTransaction:
    """A set of output files that are committed together or not at all.

    Use as a context manager: the files are committed when the block ends normally and
    aborted (every staged file removed, folders it created removed again when empty) when it
    raises, including KeyboardInterrupt.

    Examples
    --------
    >>> with OutputTransaction() as tx:                                    # doctest: +SKIP
    ...     write_surface(surface, "out/bone.stl", transaction=tx)
    ...     write_text(report_json, "out/report.json", transaction=tx)
    """

    def __init__(self):
        self._staged: list = []      # [(final path, temporary path)]
        self._created: list = []     # [(mark when created, folder)], in creation order
        self._swept: set = set()
        self.state = "open"

    # -- staging

    def stage(self, path: PathLike) -> str:
        """Reserve ``path`` in this transaction and return the temporary file to write.

        The temporary file exists (empty, mode 0666 minus the umask) in the destination's
        folder, which is created when missing, and keeps the destination's extension (some
        writers choose the format by it).

        Raises
        ------
        InputError
            ``path`` is already an output of this transaction.
        OutputError
            The path is a folder, its name is too long, or the folder cannot be created or
            written.
        """
        self._check_open()
        final = os.path.abspath(os.fspath(path))
        if any(final == done for done, _ in self._staged):
            raise InputError(f"Two outputs of this run are the same file {final}; give them "
                             "different names.")
        base = os.path.basename(final)
        if not base:
            raise OutputError(f"Cannot write {final}: no file name; give a file name.")
        if os.path.isdir(final):
            raise OutputError(f"Cannot write {final}: it is a folder; give a file name, not a "
                              "folder.")
        folder = os.path.dirname(final)
        self._make_folder(folder, final)
        name_max = _name_max(folder)
        if len(base.encode()) > name_max:
            raise OutputError(f"Cannot write {final}: the file name is {len(base.encode())} "
                              f"bytes long, the file system allows {name_max}; choose a "
                              "shorter name.")
        if folder not in self._swept:
            self._swept.add(folder)
            remove_stale(folder)
        ext = extension(base) or os.path.splitext(base)[1]
        while True:
            tmp = os.path.join(folder, _temp_name(base, ext, "part", name_max))
            try:
                # O_EXCL: never reuse another writer's file; the mode is filtered by the umask.
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, NEW_FILE_MODE)
            except FileExistsError:
                continue
            except OSError as exc:
                raise output_error(final, exc) from None
            os.close(fd)
            break
        self._staged.append((final, tmp))
        return tmp

    def write(self, path: PathLike, writer: Callable[[str], object]) -> str:
        """Stage ``path`` and call ``writer(temporary_path)``; return the final path.

        An OSError becomes an OutputError naming ``path`` (not the temporary file); the
        staged file stays in the transaction, which the caller aborts.
        """
        tmp = self.stage(path)
        final = self._staged[-1][0]
        try:
            writer(tmp)
        except OSError as exc:
            if isinstance(exc, (InputError, OutputError)):
                raise
            raise output_error(final, exc, temporary=tmp) from exc
        return final

    def _make_folder(self, folder: str, final: str) -> None:
        missing = []
        head = folder
        while head and not os.path.isdir(head):
            if os.path.lexists(head):
                raise OutputError(f"Cannot write {final}: {head} is a file, not a folder; "
                                  "choose another output folder.")
            missing.append(head)
            parent = os.path.dirname(head)
            if parent == head:
                break
            head = parent
        for new in reversed(missing):
            try:
                os.mkdir(new)
            except FileExistsError:
                continue
            except OSError as exc:
                raise output_error(final, exc, "create the folder of") from None
            self._created.append((len(self._staged), new))

    # -- savepoints

    def mark(self) -> int:
        """A savepoint: :meth:`discard` removes what was staged after it."""
        return len(self._staged)

    def discard(self, mark: int = 0) -> None:
        """Remove the files staged after ``mark`` (they will not be committed), and the
        folders created for them when they are empty."""
        for _, tmp in self._staged[mark:]:
            _remove_quietly(tmp)
        del self._staged[mark:]
        while self._created and self._created[-1][0] >= mark:
            _, folder = self._created.pop()
            try:
                os.rmdir(folder)
            except OSError:  # not empty: another output of this transaction is in it
                pass

    @property
    def paths(self) -> List[str]:
        """The final paths staged so far."""
        return [final for final, _ in self._staged]

    # -- end

    def commit(self) -> List[str]:
        """Rename every staged file onto its destination; return the destinations.

        Every staged file must hold data. Should a rename fail, the destinations already
        replaced get their previous content back (kept as hard links until the end), the
        staged files are removed and OutputError is raised: the transaction is all or nothing.
        """
        self._check_open()
        with critical_section():
            try:
                for final, tmp in self._staged:
                    try:
                        empty = os.path.getsize(tmp) == 0
                    except OSError as exc:
                        raise output_error(final, exc) from None
                    if empty:
                        raise OutputError(f"Cannot write {final}: the writer produced no "
                                          "data; check the disk and try again.")
                done = []  # [(final, backup or None)]
                try:
                    for final, tmp in self._staged:
                        backup = self._backup(final)
                        try:
                            os.replace(tmp, final)
                        except OSError as exc:
                            if backup:
                                _remove_quietly(backup)
                            raise output_error(final, exc) from None
                        done.append((final, backup))
                except BaseException:
                    for final, backup in reversed(done):
                        if backup:
                            try:
                                os.replace(backup, final)
                            except OSError:
                                pass
                        else:
                            _remove_quietly(final)
                    raise
                for _, backup in done:
                    if backup:
                        _remove_quietly(backup)
            except BaseException:
                self._abort()
                raise
            self.state = "committed"
            return [final for final, _ in self._staged]

    def abort(self) -> None:
        """Remove every staged file and the folders this transaction created (when empty)."""
        if self.state == "open":
            with critical_section():
                self._abort()

    def _abort(self) -> None:
        self.discard(0)
        self.state = "aborted"

    def _backup(self, final: str) -> Optional[str]:
        """A hard link to the current ``final`` (None when there is none or links fail)."""
        if not os.path.isfile(final):
            return None
        folder, base = os.path.split(final)
        ext = extension(base) or os.path.splitext(base)[1]
        backup = os.path.join(folder, _temp_name(base, ext, "prev", _name_max(folder)))
        try:
            os.link(final, backup)
        except OSError:
            return None
        return backup

    def _check_open(self) -> None:
        if self.state != "open":
            raise RuntimeError(f"the output transaction is already {self.state}")

    def __enter__(self) -> "OutputTransaction":
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            if self.state == "open":
                self.commit()
        else:
            self.abort()
        return False


def _remove_quietly(path: str) -> None:
    try:
        os.remove(path)
    except FileNotFoundError:
        pass
    except OSError:
        pass


# ----------------------------------------------------------------------------------------
# one file

@contextlib.contextmanager
def atomic_path(path: PathLike, transaction: Optional[OutputTransaction] = None):
    """Yield a temporary path beside ``path``; it becomes ``path`` only on success.

    Without ``transaction`` the file is committed when the block ends (a one-file
    transaction) and removed on any exception (including KeyboardInterrupt). With one, the
    file is staged into it and the caller's transaction commits or aborts it.

    Parameters
    ----------
    path : str or os.PathLike
        The final file. Its folder must exist (InputError otherwise) unless a transaction is
        given, which creates it.
    transaction : OutputTransaction, optional
    """
    if transaction is not None:
        yield transaction.stage(path)
        return
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder):
        raise InputError(f"Output folder does not exist: {folder}")
    with OutputTransaction() as tx:
        yield tx.stage(path)


def write_text(text: str, path: PathLike,
               transaction: Optional[OutputTransaction] = None) -> None:
    """Write a text file atomically (reports, summaries), or stage it into ``transaction``."""
    def write(tmp):
        with open(tmp, "w", encoding="utf-8", newline="") as f:
            f.write(text)
    if transaction is not None:
        transaction.write(path, write)
        return
    with OutputTransaction() as tx:
        tx.write(path, write)


def ensure_folder(path: PathLike) -> str:
    """Create the folder of ``path`` if needed; return ``path``.

    Raises OutputError (naming the folder) when it cannot be created.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as exc:
        raise output_error(folder, exc, "create the folder") from None
    return path


# Characters a name part keeps as they are (a leading '.' is escaped: no hidden files, and
# '.' / '..' never become the current or parent folder).
_NAME_SAFE = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_.")


def name_part(text) -> str:
    """``text`` (a segment or case name) as a part of a file name, one-to-one.

    ASCII letters, digits, ``-``, ``_`` and ``.`` (except a leading one) are kept; every other
    byte of the UTF-8 text, ``%`` included, becomes ``%XX``, as in a URL. Distinct names so
    give distinct file names (``.`` -> ``%2E``, ``..`` -> ``%2E.``, ``a b`` -> ``a%20b``,
    ``a/b`` -> ``a%2Fb``), and :func:`name_from_part` gives the name back. The empty name
    becomes ``%``, which no other name gives.
    """
    text = str(text)
    if not text:
        return "%"
    out = []
    for i, char in enumerate(text):
        if char in _NAME_SAFE and not (i == 0 and char == "."):
            out.append(char)
        else:
            out.extend(f"%{byte:02X}" for byte in char.encode("utf-8"))
    return "".join(out)


def name_from_part(part: str) -> str:
    """The inverse of :func:`name_part`."""
    if part == "%":
        return ""
    data = bytearray()
    i = 0
    while i < len(part):
        if part[i] == "%":
            data.append(int(part[i + 1:i + 3], 16))
            i += 3
        else:
            data.extend(part[i].encode("ascii"))
            i += 1
    return data.decode("utf-8")


def extension(name: PathLike) -> str:
    """Lower-case extension, with the double extensions this module knows (.seg.nrrd, .nii.gz)."""
    low = os.fspath(name).lower()
    for double in (".seg.nrrd", ".nii.gz"):
        if low.endswith(double):
            return double
    return os.path.splitext(low)[1]
