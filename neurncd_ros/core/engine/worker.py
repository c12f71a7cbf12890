"""A background worker that runs a stage's next job whenever it is woken.

The stage decides what the next job is (newest first, keyframes first, ...):
``step(cancel)`` takes it and returns True when it did something, False when
there was nothing to do. The worker never dies of a job: a ValueError (bad
input) is a reported problem, anything else a reported error, and the loop
goes on. ``stop()`` sets ``cancel`` (a long job checks it) and joins.
"""

from __future__ import annotations

import threading
from typing import Callable

from .health import Health


class Worker:
    """One background thread running ``step(cancel)`` each time it is woken (module doc)."""
    def __init__(self, name: str, step: Callable[[threading.Event], bool], health: Health,
                 idle_wait_s: float = 0.1) -> None:
        self.name = name
        self._step = step
        self.health = health
        self.idle_wait_s = idle_wait_s
        self.cancel = threading.Event()
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self.busy = False

    def start(self) -> "Worker":
        self._thread = threading.Thread(target=self._loop, name=self.name, daemon=True)
        self._thread.start()
        return self

    def notify(self) -> None:
        self._wake.set()

    def _loop(self) -> None:
        while not self.cancel.is_set():
            try:
                self.busy = True
                did = self._step(self.cancel)
            except ValueError as err:
                self.health.problem("skipped", f"{self.name}: {err}")
                did = True
            except Exception as err:  # noqa: BLE001 - one bad job must not end the loop
                if self.cancel.is_set():
                    break
                self.health.problem("job_error", f"{self.name} failed on a job: {err!r}", 2)
                did = True
            finally:
                self.busy = False
            if not did:
                self._wake.wait(self.idle_wait_s)
                self._wake.clear()

    def stop(self, timeout: float = 5.0) -> bool:
        """Cancel and join; True if the thread ended within ``timeout``."""
        self.cancel.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()
