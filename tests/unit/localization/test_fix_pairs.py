"""The transform's window of pairs as columns, against the bounded deque it replaced."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.localization.fix_pairs import PairColumns

Row = tuple[float, float, float, float, float, float, float, int]

operations = st.lists(
    st.one_of(
        st.tuples(
            st.just("append"),
            st.floats(0.0, 1.0),  # time step
            st.integers(0, 4),  # segment
            st.floats(-100.0, 100.0),
        ),
        st.tuples(st.just("drop"), st.floats(0.0, 3.0), st.just(0), st.just(0.0)),
    ),
    max_size=120,
)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 12), operations)
def test_the_columns_hold_what_a_bounded_deque_of_rows_holds(
    max_pairs: int, ops: list[tuple[str, float, int, float]]
) -> None:
    columns = PairColumns(max_pairs)
    model: deque[Row] = deque(maxlen=max_pairs)
    now = 0.0
    for kind, step, segment, value in ops:
        if kind == "append":
            now += step
            row: Row = (
                now,
                value,
                -value,
                2 * value,
                value + 1,
                value / 7,
                1.0 + abs(value),
                segment,
            )
            model.append(row)
            columns.append(row[0], (row[1], row[2]), (row[3], row[4]), row[5], row[6], segment)
        else:
            while model and model[0][0] < now - step:
                model.popleft()
            columns.drop_older_than(now - step)
        assert len(columns) == len(model)
        if not model:
            continue
        rows = np.array([r[:7] for r in model])
        for got, want in zip(
            (
                columns.time_s,
                columns.global_x,
                columns.global_y,
                columns.local_x,
                columns.local_y,
                columns.yaw_diff_rad,
                columns.weight,
            ),
            rows.T,
            strict=True,
        ):
            assert np.array_equal(got, want)
        labels, index, counts = columns.segments()
        unique, inverse, unique_counts = np.unique(
            [r[7] for r in model], return_inverse=True, return_counts=True
        )
        assert labels == unique.tolist()
        assert np.array_equal(index, inverse.reshape(-1))
        assert np.array_equal(counts, unique_counts)
        assert np.array_equal(columns.segment, [r[7] for r in model])


def test_the_columns_are_read_only_views_and_a_bound_is_needed() -> None:
    columns = PairColumns(3)
    columns.append(0.0, (1.0, 2.0), (3.0, 4.0), 0.0, 1.0, 0)
    with pytest.raises(ValueError, match="read-only"):
        columns.time_s[0] = 5.0
    with pytest.raises(ValueError, match="at least 1"):
        PairColumns(0)
