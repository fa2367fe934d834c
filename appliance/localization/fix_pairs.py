"""The local/global transform's window of fix/odometry pairs, kept as columns.

Every fit of the transform (``frame_blend``: every ``estimate_period_s``, and at every fix
while the window is young) reads every pair of the last ``window_s``, about 200 at
10 Hz. Kept as a row of Python objects per pair, the fit spent most of its time turning
them back into arrays, inside the control cycle that took the fix. Here each pair is
written once into a numpy buffer as it is taken, and the fit reads its columns as
views. Pure: no I/O, no clock.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

_TIME, _GLOBAL_X, _GLOBAL_Y, _LOCAL_X, _LOCAL_Y, _YAW_DIFF, _WEIGHT, _SEGMENT = range(8)


class PairColumns:
    """Pairs in time order: appended at the end, dropped from the front, at most
    ``max_pairs`` of them (the oldest goes, as a bounded deque's would)."""

    def __init__(self, max_pairs: int) -> None:
        if max_pairs < 1:
            raise ValueError(f"max_pairs must be at least 1, got {max_pairs}")
        self.max_pairs = max_pairs
        # Room for as many again, so that moving the pairs to the front is rare.
        self._buffer = np.empty((8, 2 * max_pairs))
        self._start = 0
        self._end = 0
        self._segment_counts: dict[int, int] = {}  # pairs in the window, per segment

    def __len__(self) -> int:
        return self._end - self._start

    def append(
        self,
        time_s: float,
        global_xy: tuple[float, float],
        local_xy: tuple[float, float],
        yaw_diff_rad: float,
        weight: float,
        segment: int,
    ) -> None:
        if self._end - self._start == self.max_pairs:
            self._drop_first()
        if self._end == self._buffer.shape[1]:
            count = self._end - self._start
            self._buffer[:, :count] = self._buffer[:, self._start : self._end]
            self._start, self._end = 0, count
        self._buffer[:, self._end] = (
            time_s,
            global_xy[0],
            global_xy[1],
            local_xy[0],
            local_xy[1],
            yaw_diff_rad,
            weight,
            segment,
        )
        self._end += 1
        self._segment_counts[segment] = self._segment_counts.get(segment, 0) + 1

    def _drop_first(self) -> None:
        segment = int(self._buffer[_SEGMENT, self._start])
        self._start += 1
        left = self._segment_counts[segment] - 1
        if left:
            self._segment_counts[segment] = left
        else:
            del self._segment_counts[segment]

    def drop_older_than(self, time_s: float) -> None:
        """Drop the pairs from the front while they are older than ``time_s``."""
        times = self._buffer[_TIME]
        while self._start < self._end and times[self._start] < time_s:
            self._drop_first()

    def _column(self, index: int) -> FloatArray:
        view: FloatArray = self._buffer[index, self._start : self._end]
        view.flags.writeable = False
        return view

    @property
    def time_s(self) -> FloatArray:
        return self._column(_TIME)

    @property
    def global_x(self) -> FloatArray:
        return self._column(_GLOBAL_X)

    @property
    def global_y(self) -> FloatArray:
        return self._column(_GLOBAL_Y)

    @property
    def local_x(self) -> FloatArray:
        return self._column(_LOCAL_X)

    @property
    def local_y(self) -> FloatArray:
        return self._column(_LOCAL_Y)

    @property
    def yaw_diff_rad(self) -> FloatArray:
        return self._column(_YAW_DIFF)

    @property
    def weight(self) -> FloatArray:
        return self._column(_WEIGHT)

    @property
    def segment(self) -> NDArray[np.int_]:
        return self._column(_SEGMENT).astype(np.int_)

    def segments(self) -> tuple[list[int], NDArray[np.intp], NDArray[np.intp]]:
        """The segments in the window in increasing order, each pair's index into them
        and each one's number of pairs (``np.unique``'s answer, kept as pairs come and go)."""
        labels = sorted(self._segment_counts)
        index = np.searchsorted(np.array(labels, dtype=np.float64), self._column(_SEGMENT))
        counts = np.array([self._segment_counts[label] for label in labels], dtype=np.intp)
        return labels, index, counts
