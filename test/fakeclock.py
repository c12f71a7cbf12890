"""A hand-driven monotonic clock for tests of the engine and the pairing (seconds in ``t``)."""

MS = 1_000_000  # nanoseconds per millisecond, for stamps


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t
