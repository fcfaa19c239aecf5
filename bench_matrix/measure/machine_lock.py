"""One timing phase per machine: a host-wide `flock` every measuring process holds while it times a cell; and
one run at a time measuring a model into a store (`store_lock`).

The lock lives in /tmp/bench-matrix (or `$BENCH_MATRIX_LOCK_DIR`), shared by every store, workspace and user
of the host. The kernel drops a `flock` when its holder's file closes, so a killed run never leaves it held.
"""

from __future__ import annotations

import fcntl
import getpass
import hashlib
import json
import os
import platform
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from bench_matrix.errors import UserError

LOCK_DIR_VARIABLE = "BENCH_MATRIX_LOCK_DIR"
DEFAULT_LOCK_DIR = Path("/tmp/bench-matrix")  # not $TMPDIR: every user of the host must find the same file
LOCK_FILE, HOLDER_FILE = "timing.lock", "timing.holder.json"
REMIND_EVERY_S = 30.0


@dataclass
class TimingWindow:
    """When this process held the machine's timing slot (wall clock, `time.time()`) and how long it waited."""

    waited_s: float
    start: float
    end: float | None = None  # set when the slot is released

    def as_dict(self) -> dict[str, float | None]:
        return asdict(self)


def lock_dir() -> Path:
    """The directory of the host-wide lock: `$BENCH_MATRIX_LOCK_DIR`, else /tmp/bench-matrix."""
    return Path(os.environ.get(LOCK_DIR_VARIABLE) or DEFAULT_LOCK_DIR)


@contextmanager
def timing_slot(holder: str, on_wait: Callable[[str], None] | None = None) -> Iterator[TimingWindow]:
    """Hold the machine's timing slot for the block; `holder` is what a waiting run shows. `on_wait(message)`
    is called when the slot is taken (and every 30 s while waiting, from a helper thread)."""
    directory = _shared_dir(lock_dir())
    lock = _open_lock(directory / LOCK_FILE)
    try:
        waited_s = _acquire(lock, directory, on_wait)
        window = TimingWindow(waited_s=waited_s, start=time.time())
        sidecar = _open_sidecar(directory / HOLDER_FILE)
        _write_holder(sidecar, holder, window.start)
        try:
            yield window
        finally:
            window.end = time.time()  # before the release: windows of successive holders never overlap
            _clear_holder(sidecar)
    finally:
        os.close(lock)  # drops the flock


@dataclass(frozen=True)
class Holder:
    """The process that holds the timing slot, as its sidecar names it."""

    pid: int
    user: str
    holder: str  # what the holding run is timing (matrix file, model, cell)
    since: float  # wall clock, time.time()


def waiting_message(directory: Path, waited_s: float = 0.0) -> str:
    """What a waiting run shows: the live holder named in the sidecar, or that it did not name itself."""
    found = current_holder(directory)
    if found is None:
        text = f"waiting for the machine's timing lock ({directory / LOCK_FILE}), held by an unnamed process"
    else:
        since = time.strftime("%H:%M:%S", time.localtime(found.since))
        text = (f"waiting for the timing phase of pid {found.pid} of user {found.user} "
                f"({found.holder}, since {since})")
    return text if waited_s < 1 else f"{text}; waited {_duration(waited_s)}"


def store_lock(store: Path, model: str, block: bool, on_wait: Callable[[], None]) -> int | None:
    """Take the host-wide lock held while measuring `model` into `store` (rounds until records stored): the
    descriptor whose closing frees it, or None if busy and not `block`; `on_wait()` runs before blocking."""
    name = hashlib.sha256(f"{store.resolve()}\0{model}".encode()).hexdigest()[:20]
    lock = _open_lock(_shared_dir(lock_dir()) / f"store-{name}.lock")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return lock
    except BlockingIOError:
        if not block:
            os.close(lock)
            return None
    on_wait()
    fcntl.flock(lock, fcntl.LOCK_EX)
    return lock


def current_holder(directory: Path) -> Holder | None:
    """The live holder the sidecar names; None if it is empty, unreadable, from another host or stale."""
    try:
        text = (directory / HOLDER_FILE).read_text(errors="replace")
        info, _ = json.JSONDecoder().raw_decode(text)  # a shorter rewrite may leave an old tail after it
        found = Holder(int(info["pid"]), str(info["user"]), str(info["holder"]), float(info["since"]))
        started, host = info["started"], info["host"]
    except (OSError, ValueError, TypeError, KeyError):
        return None
    if started is None or host != platform.node() or _start_ticks(found.pid) != started:
        return None  # ended, or its pid now belongs to another process
    return found


def _acquire(lock: int, directory: Path, on_wait: Callable[[str], None] | None) -> float:
    """Take the flock, blocking in the kernel (no polling) once it is busy; the seconds waited."""
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return 0.0
    except BlockingIOError:
        pass
    begin = time.monotonic()
    if on_wait is None:
        fcntl.flock(lock, fcntl.LOCK_EX)
    else:
        on_wait(waiting_message(directory))
        with _reminders(directory, on_wait, begin):
            fcntl.flock(lock, fcntl.LOCK_EX)
    return time.monotonic() - begin


@contextmanager
def _reminders(directory: Path, on_wait: Callable[[str], None], begin: float) -> Iterator[None]:
    """Repeat the waiting message every REMIND_EVERY_S from a thread that sleeps in between (naming the
    current holder: it may have changed)."""
    stop = threading.Event()

    def remind() -> None:
        while not stop.wait(REMIND_EVERY_S):
            on_wait(waiting_message(directory, time.monotonic() - begin))

    thread = threading.Thread(target=remind, name="timing-lock-wait", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


def _shared_dir(directory: Path) -> Path:
    """The lock directory, created sticky and writable by every user (mode 1777, like /tmp) when it is new."""
    try:
        directory.mkdir(parents=True)
        os.chmod(directory, 0o1777)
    except FileExistsError:
        pass
    except OSError as exc:
        raise _unusable(directory, exc) from exc
    return directory


def _open_lock(path: Path) -> int:
    """The lock file opened for `flock` (read access is enough); created readable by every user."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as exc:
        raise _unusable(path.parent, exc) from exc
    _widen(fd, 0o644)
    return fd


def _open_sidecar(path: Path) -> int | None:
    """The holder file opened for writing (mode 666: any user's run can name itself); None if not writable."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
    except OSError:
        return None  # the lock still works; waiting runs just cannot say who holds it
    _widen(fd, 0o666)
    return fd


def _widen(fd: int, mode: int) -> None:
    """Give our own file `mode` despite the umask; another user's file is left as it is."""
    if os.fstat(fd).st_uid == os.getuid():
        os.fchmod(fd, mode)


def _write_holder(fd: int | None, holder: str, since: float) -> None:
    """Name this process in the sidecar: written over the old text, then cut to length (never empty)."""
    if fd is None:
        return
    text = json.dumps({"pid": os.getpid(), "started": _start_ticks(os.getpid()), "host": platform.node(),
                       "user": _user(), "holder": holder, "since": since}).encode()
    try:
        os.pwrite(fd, text, 0)
        os.ftruncate(fd, len(text))
    except OSError:  # a full disk: the slot is held all the same, just not named
        pass


def _clear_holder(fd: int | None) -> None:
    if fd is not None:
        os.ftruncate(fd, 0)
        os.close(fd)


def _start_ticks(pid: int) -> int | None:
    """The process's start time in clock ticks since boot (field 22 of /proc/PID/stat); None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return int(fields[19])  # fields after "(comm)" start at field 3


def _user() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return str(os.getuid())


def _duration(seconds: float) -> str:
    minutes, rest = divmod(int(seconds), 60)
    return f"{minutes} min {rest} s" if minutes else f"{rest} s"


def _unusable(directory: Path, exc: OSError) -> UserError:
    return UserError(f"cannot use the machine's timing lock in {directory}: {exc.strerror or exc}; make "
                     f"that directory writable by every user (chmod 1777) or set {LOCK_DIR_VARIABLE} to one "
                     f"that is")
