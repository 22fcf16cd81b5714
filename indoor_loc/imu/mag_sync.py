"""Merge the IMU stream and a magnetometer at its own rate into one stamp-ordered event stream.

Phones and many robot IMUs publish ``imu/mag`` at its own rate (a quarter of the gyroscope's on a
Nexus 5) with its own stamps, and the two topics reach a node out of step: a magnetometer message may
arrive after IMU messages with later stamps. A filter that wants each magnetometer sample once, at its
stamp, needs the two streams merged in stamp order. :class:`MagSync` does it online with a bounded
wait, :func:`merge_events` is the batch equivalent, and both give the same order:

- an IMU sample at ``t`` is released once a magnetometer sample with stamp ≥ ``t`` arrived (so every
  magnetometer sample up to ``t`` is known), or once the IMU stream has run ``max_delay_s`` past
  ``t`` (the magnetometer is missing or slow: do not wait longer), or at once while no magnetometer
  sample was ever seen (a 6-D robot IMU gets no latency at all);
- a magnetometer sample at ``t_m`` is released once an IMU sample with stamp > ``t_m`` arrived (it
  goes after every IMU sample up to and including ``t_m``);
- a magnetometer sample whose stamp lies before an IMU sample already released is *late*: it is
  dropped and counted (``n_late``), never applied out of order.

So online = batch whenever no magnetometer sample is later than ``max_delay_s`` (in IMU stamp time)
and the first one is not late (before it, IMU samples are not held).
Times are int nanoseconds.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from indoor_loc.errors import InvalidInputError

IMU = 0
MAG = 1


@dataclass
class MagSyncState:
    """Queues and counters of :class:`MagSync` (copy with :meth:`copy`)."""

    imu: deque[tuple[int, Any]] = field(default_factory=deque)      # (t_ns, payload)
    mag: deque[tuple[int, Any]] = field(default_factory=deque)      # (t_ns, payload)
    last_imu_in_ns: int | None = None
    last_mag_in_ns: int | None = None
    last_released_imu_ns: int | None = None
    seen_mag: bool = False
    n_late: int = 0

    def copy(self) -> "MagSyncState":
        return MagSyncState(deque(self.imu), deque(self.mag), self.last_imu_in_ns, self.last_mag_in_ns,
                            self.last_released_imu_ns, self.seen_mag, self.n_late)


class MagSync:
    """Online stamp-order merge of IMU and magnetometer samples (see the module docstring).

    ``push_imu``/``push_mag`` return the events now ready, in stamp order, as ``(kind, t_ns,
    payload)`` with ``kind`` :data:`IMU` or :data:`MAG`; ``flush`` releases everything held."""

    def __init__(self, max_delay_s: float = 0.1) -> None:
        if not (max_delay_s >= 0.0):
            raise ValueError(f"max_delay_s: expected >= 0, got {max_delay_s}")
        self.max_delay_ns = int(round(max_delay_s * 1e9))
        self._st = MagSyncState()

    # -- input --------------------------------------------------------------------------------------
    def push_imu(self, t_ns: int, payload: Any) -> list[tuple[int, int, Any]]:
        st = self._st
        if st.last_imu_in_ns is not None and t_ns <= st.last_imu_in_ns:
            raise InvalidInputError("non_monotonic_stamp", f"IMU stamps must increase: {t_ns} ns after {st.last_imu_in_ns} ns")
        st.last_imu_in_ns = t_ns
        st.imu.append((t_ns, payload))
        return self._release()

    def push_mag(self, t_ns: int, payload: Any) -> list[tuple[int, int, Any]]:
        """Queue a magnetometer sample; returns the events now ready. A sample older than an IMU
        sample already released is counted late and dropped (returns what is ready anyway)."""
        st = self._st
        if st.last_mag_in_ns is not None and t_ns <= st.last_mag_in_ns:
            raise InvalidInputError("non_monotonic_stamp", f"magnetometer stamps must increase: {t_ns} ns after {st.last_mag_in_ns} ns")
        st.last_mag_in_ns = t_ns
        if st.last_released_imu_ns is not None and t_ns < st.last_released_imu_ns:
            st.n_late += 1
            return []
        st.seen_mag = True
        st.mag.append((t_ns, payload))
        return self._release()

    def flush(self) -> list[tuple[int, int, Any]]:
        """Release everything held, in stamp order (end of input)."""
        out = []
        st = self._st
        while st.imu or st.mag:
            if st.mag and (not st.imu or st.mag[0][0] < st.imu[0][0]):
                t, p = st.mag.popleft()
                out.append((MAG, t, p))
            else:
                t, p = st.imu.popleft()
                st.last_released_imu_ns = t
                out.append((IMU, t, p))
        return out

    # -- merge --------------------------------------------------------------------------------------
    def _release(self) -> list[tuple[int, int, Any]]:
        st = self._st
        out = []
        newest_imu = st.last_imu_in_ns
        newest_mag = st.last_mag_in_ns if st.seen_mag else None
        while True:
            if st.mag and st.imu and st.mag[0][0] < st.imu[0][0]:
                t, p = st.mag.popleft()                 # the IMU stream has passed it
                out.append((MAG, t, p))
                continue
            if st.mag and not st.imu and newest_imu is not None and st.mag[0][0] < newest_imu:
                t, p = st.mag.popleft()
                out.append((MAG, t, p))
                continue
            if st.imu:
                t = st.imu[0][0]
                ready = (not st.seen_mag or (newest_mag is not None and newest_mag >= t)
                         or (newest_imu is not None and newest_imu - t >= self.max_delay_ns))
                if ready:
                    t, p = st.imu.popleft()
                    st.last_released_imu_ns = t
                    out.append((IMU, t, p))
                    continue
            break
        # a held magnetometer sample now older than a released IMU sample cannot be applied in order
        return out

    # -- state --------------------------------------------------------------------------------------
    @property
    def n_late(self) -> int:
        """Magnetometer samples dropped because they arrived after later IMU samples were used."""
        return self._st.n_late

    @property
    def n_held(self) -> int:
        return len(self._st.imu) + len(self._st.mag)

    def state(self) -> MagSyncState:
        return self._st.copy()

    def set_state(self, state: MagSyncState) -> None:
        self._st = state.copy()


def merge_events(t_ns: np.ndarray, mag_t_ns: np.ndarray | None) -> list[tuple[int, int]]:
    """Batch order of :class:`MagSync`: ``(kind, index)`` pairs over IMU samples ``t_ns`` (N,) and
    magnetometer samples ``mag_t_ns`` (M,), both strictly increasing int ns. A magnetometer sample
    goes after every IMU sample with a stamp ≤ its own."""
    t = np.asarray(t_ns, dtype=np.int64)
    if mag_t_ns is None or len(mag_t_ns) == 0:
        return [(IMU, i) for i in range(len(t))]
    mt = np.asarray(mag_t_ns, dtype=np.int64)
    # position of each mag sample: after the IMU samples with stamp <= t_m
    after = np.searchsorted(t, mt, side="right")
    out: list[tuple[int, int]] = []
    j = 0
    for i in range(len(t)):
        while j < len(mt) and after[j] <= i:
            out.append((MAG, j))
            j += 1
        out.append((IMU, i))
    while j < len(mt):
        out.append((MAG, j))
        j += 1
    return out
