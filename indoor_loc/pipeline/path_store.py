"""The newest poses of a published path, kept as arrays (the bounded history of long runs).

A path an estimator republishes (``pf/path``, ``pdr_kf/path``) holds at most its ``path_max_poses``
newest poses. Kept as Python objects (a ``tracker.Estimate`` with its arrays, about 460 bytes; a
``(stamp, x, y, yaw)`` tuple, about 190 bytes) a full path of 20 000 poses is 4–9 MB per user, which
a live node grows into over its first hours (its memory climbing for ~1.8 h of walking). Here a pose
is 5 float64 = 40 bytes in a preallocated ring, so the whole bound costs 0.8 MB from the start and
memory does not climb: the rule (the newest ``cap`` poses; older ones dropped and counted in
:attr:`PathStore.dropped`) and the published paths are the same as before.
"""
from __future__ import annotations

import numpy as np


class PathStore:
    """A ring of the newest ``cap`` poses ``(stamp ns, x, y, yaw, z)``, in the order they were added."""

    def __init__(self, cap: int) -> None:
        if cap < 1:
            raise ValueError(f"PathStore: expected cap >= 1, got {cap}")
        self.cap = int(cap)
        self._stamps = np.zeros(self.cap, np.int64)
        self._vals = np.zeros((self.cap, 4))      # x, y, yaw, z
        self._head = 0                            # index of the oldest pose
        self._n = 0
        #: poses pushed out by newer ones (the bound's counted drop)
        self.dropped = 0

    def __len__(self) -> int:
        return self._n

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays (fixed: the bound's whole cost)."""
        return int(self._stamps.nbytes + self._vals.nbytes)

    def clear(self) -> None:
        self._head = self._n = 0

    def extend(self, stamps: np.ndarray, xy: np.ndarray, yaw: np.ndarray, z: np.ndarray) -> None:
        """Append poses (stamps (K,) ns, xy (K, 2) m, yaw (K,) rad, z (K,) m), oldest first."""
        stamps = np.asarray(stamps, np.int64).reshape(-1)
        k = len(stamps)
        if k == 0:
            return
        vals = np.column_stack([np.asarray(xy, float).reshape(-1, 2), np.asarray(yaw, float).reshape(-1),
                                np.asarray(z, float).reshape(-1)])
        if k >= self.cap:                         # only the newest cap of them can stay
            self.dropped += self._n + k - self.cap
            self._stamps[:] = stamps[-self.cap:]
            self._vals[:] = vals[-self.cap:]
            self._head, self._n = 0, self.cap
            return
        over = max(0, self._n + k - self.cap)
        self.dropped += over
        self._head = (self._head + over) % self.cap
        self._n -= over
        idx = (self._head + self._n + np.arange(k)) % self.cap
        self._stamps[idx] = stamps
        self._vals[idx] = vals
        self._n += k

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Copies of the poses, oldest first: stamps (T,), xy (T, 2), yaw (T,), z (T,)."""
        idx = (self._head + np.arange(self._n)) % self.cap
        v = self._vals[idx]
        return self._stamps[idx].copy(), v[:, :2].copy(), v[:, 2].copy(), v[:, 3].copy()
