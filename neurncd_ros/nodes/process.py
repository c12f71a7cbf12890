"""How a node process starts and stops: signals, exit codes and what a killed one leaves.

Standard library only, so that a node module can take over SIGINT and SIGTERM before it
imports anything heavy (:class:`Shutdown`); :func:`exit_status` reports a child's end as a
shell does, and :func:`remove_stale_shm` frees the shared memory of Fast DDS processes that
died without removing it.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Shutdown:
    """SIGINT and SIGTERM handled explicitly, also when the process started with SIGINT
    ignored (``cmd &`` from a script, nohup, some supervisors), where Python installs no
    KeyboardInterrupt.

    Two phases. While the process is *starting* (``install(starting=True)`` until
    :meth:`started`: the imports, torch's take seconds, and the checks before rclpy.init)
    a signal ends it at once with exit code 0: nothing has been opened or written that
    would need closing, and ``os._exit`` is the one way out that no library's import code
    can catch or turn into a traceback (an exception raised from the handler inside torch's
    import could be swallowed by its ``except`` clauses, or end in a traceback). Once
    started, the first signal asks for a clean stop (``requested``: the node stops its
    workers, saves, logs its summary and exits 0); a second one exits at once.
    """

    def __init__(self, name: str = "") -> None:
        self.name = name
        self.requested = threading.Event()
        self.signal_name = ""
        self._starting = False

    def install(self, starting: bool = False) -> "Shutdown":
        """Take over SIGINT and SIGTERM (``starting``: in the exit-at-once phase)."""
        self._starting = starting
        for sig in STOP_SIGNALS:
            signal.signal(sig, self._handle)
        # bringup starts its children with these signals blocked, so that one sent before
        # this line waits (pending) for the handler instead of meeting the interpreter's
        # default KeyboardInterrupt; now that the handler is in place, let it through.
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
        return self

    def started(self) -> None:
        """From now on a signal asks for a clean stop instead of exiting at once."""
        self._starting = False

    def _handle(self, signum, frame) -> None:
        name = signal.Signals(signum).name
        if self._starting:
            # os.write, not print: the handler may run in the middle of a print.
            os.write(2, f"{self.name or 'process'}: {name} while starting: exiting\n".encode())
            os._exit(0)
        if self.requested.is_set():
            os._exit(128 + signum)
        self.signal_name = name
        self.requested.set()


def exit_status(returncode: int) -> tuple[int, str]:
    """A child's ``Popen.returncode`` as a shell would report it: (exit code, description).

    A child killed by a signal has a negative returncode (-9); passed on as an exit code it
    would be masked to a byte (247), so it becomes 128 + signal number (137), as a shell
    reports it.
    """
    if returncode >= 0:
        return returncode, f"exited with code {returncode}"
    try:
        name = signal.Signals(-returncode).name
    except ValueError:
        name = f"signal {-returncode}"
    return 128 - returncode, f"was killed by {name} (exit code {128 - returncode})"


def remove_stale_shm(directory: str | Path = "/dev/shm", min_age_s: float = 60.0
                     ) -> tuple[int, int]:
    """Remove the shared-memory segments Fast DDS processes that no longer run left behind
    (what ``fastdds shm clean`` does); (segments removed, bytes freed).

    Fast DDS keeps each segment ``fastrtps_<id>`` with a lock file ``fastrtps_<id>_el``
    that its owner holds (flock) while it runs, and removes both when it stops cleanly. A
    process killed (SIGKILL, a crash, a node killed after ``--stop-timeout``) leaves them:
    with the shipped profile each is a 128 MB file in a tmpfs, that is memory, never given
    back until reboot. A lock file nobody holds, older than ``min_age_s`` (a segment is
    locked right after it is created; the age keeps one being created out of reach),
    marks such a segment; it is removed under the lock, so no process can take it meanwhile.
    Other processes' live segments are never touched.
    """
    import fcntl

    directory = Path(directory)
    removed = freed = 0
    try:
        locks = sorted(directory.glob("fastrtps_*_el"))
    except OSError:
        return 0, 0
    now = time.time()
    for lock in locks:
        seg = lock.with_name(lock.name[: -len("_el")])
        try:
            if now - lock.stat().st_mtime < min_age_s:
                continue
            fd = os.open(lock, os.O_RDWR)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # held: its process runs
            for path in (seg, directory / f"sem.{seg.name}_mutex"):
                try:
                    size = path.stat().st_size
                    path.unlink()
                    freed += size
                except OSError:
                    pass
            lock.unlink(missing_ok=True)
            removed += 1
        finally:
            os.close(fd)
    return removed, freed
