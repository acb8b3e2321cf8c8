"""What the stamps of the frames a camera sends say about its clock: frames that pair long after
their stamps (a clock behind this node's, a bag played without use_sim_time), stamps that go
back (a driver restart, a clock step) and a stamp sent again (a frozen clock). Each is a
standing warning in perception's status (WARN on /diagnostics); the frames are still used,
posed at their stamps."""

from __future__ import annotations

# A frame paired this much before the newest one: the camera's stamps went back.
JUMP_BACK_S = 1.0


class StampWatch:
    """Notes each paired frame's stamp (`note`) against this node's clock `now_ns` at pairing;
    `max_lag_s` 0: no lag check."""

    def __init__(self, max_lag_s: float) -> None:
        self.max_lag_s = float(max_lag_s)
        self.arrival_lag_s: float | None = None  # the last paired frame's, seconds
        self.newest_stamp = 0  # of the frames paired so far
        self.jumps_back = 0  # times the frames went more than JUMP_BACK_S behind the newest
        self.jumped_back_s = 0.0  # the last jump, until the stream is past its newest again
        self.repeated_stamps = 0  # frames paired with the newest frame's stamp again
        self._repeating = False  # the last frame had the newest's stamp

    def note(self, stamp: int, now_ns: int) -> tuple[bool, str | None]:
        """(whether a warning started or ended, the jump's warning when this frame went back)."""
        before = self.warnings()
        self.arrival_lag_s = (now_ns - stamp) / 1e9
        jumped = None
        if stamp < self.newest_stamp - int(JUMP_BACK_S * 1e9):
            if not self.jumped_back_s:  # a new jump (the frames after it are behind too)
                self.jumps_back += 1
                self.jumped_back_s = (self.newest_stamp - stamp) / 1e9
                jumped = self._jump_warning()
        elif stamp > self.newest_stamp:
            self.jumped_back_s = 0.0  # past the newest again
        self._repeating = stamp == self.newest_stamp
        self.repeated_stamps += self._repeating
        self.newest_stamp = max(self.newest_stamp, stamp)
        return self.warnings() != before, jumped

    def warnings(self) -> list[str]:
        repeat = (
            "the camera sent a frame with the stamp of the one before (a driver stamping with a "
            "frozen clock?): the graph fuses each stamp once, so the map stops growing"
            if self._repeating
            else None
        )
        return [w for w in (self._lag_warning(), self._jump_warning(), repeat) if w]

    def status(self) -> dict:
        lag = self.arrival_lag_s
        return {
            "arrival_lag_s": None if lag is None else round(lag, 4),
            "stamp_jumps_back": self.jumps_back,
            "stamps_repeated": self.repeated_stamps,
        }

    def _lag_warning(self) -> str | None:
        lag, limit = self.arrival_lag_s, self.max_lag_s
        if lag is None or limit <= 0 or lag <= limit:
            return None
        return (
            f"the last frame paired {lag:.1f} s after its stamp (max_stamp_lag_s {limit:g}): the "
            "camera's clock is behind this node's (hosts without time sync?) or a bag plays "
            "without use_sim_time"
        )

    def _jump_warning(self) -> str | None:
        if not self.jumped_back_s:
            return None
        return (
            f"the camera's stamps went back {self.jumped_back_s:.1f} s (a driver restart, a clock "
            "step): its frames are posed at their stamps; if its clock now differs from the "
            "poses' clock, they land off their place"
        )
