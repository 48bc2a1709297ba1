"""``comms.loss``'s counter-based draws: the array twins equal their scalar references."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from openconvoy.comms.loss import counter_state, counter_state_array, counter_uniform_from

U64 = st.integers(min_value=0, max_value=2**64 - 1)


@given(key=U64, a=st.lists(st.integers(0, 2**32), min_size=1, max_size=6), b=U64)
def test_counter_state_array_is_counter_state(key: int, a: list[int], b: int) -> None:
    words = np.array(a, dtype=np.uint64)
    states = counter_state_array(np.uint64(key), words, np.uint64(b))
    assert states.dtype == np.uint64
    assert states.tolist() == [counter_state(key, w, b) for w in a]
    # A state goes on to the same draws as the scalar one.
    assert counter_uniform_from(int(states[0]), 7, 0) == counter_uniform_from(
        counter_state(key, a[0], b), 7, 0
    )
