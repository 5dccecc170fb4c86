"""pointflow.arrays: the column-by-column reductions give what numpy's own axis reductions
give, on every kind of value the per-frame paths meet (they replaced them there)."""
from __future__ import annotations

import numpy as np
import pytest

from pointflow.arrays import column_max, column_min, finite_rows

SPECIAL = [np.nan, np.inf, -np.inf, -0.0, 0.0, 1e-45, 3.4e38, -3.4e38]


@pytest.mark.parametrize("dtype", [np.float32, np.float64, ">f4"])
@pytest.mark.parametrize("k", [1, 3, 4])
def test_same_as_numpy_axis_reductions(dtype, k):
    rng = np.random.default_rng(k)
    for n in (1, 2, 17, 4096):
        p = (rng.standard_normal((n, k)) * 100).astype(dtype)
        for _ in range(max(1, n // 8)):  # specials at random places, whole rows sometimes
            p[rng.integers(n), rng.integers(k)] = SPECIAL[rng.integers(len(SPECIAL))]
        for a in (p, p[::2], np.asfortranarray(p)):  # views and layouts the callers pass
            if not len(a):
                continue
            assert np.array_equal(finite_rows(a), np.isfinite(a).all(axis=1))
            with np.errstate(invalid="ignore"):
                want_lo, want_hi = a.min(axis=0), a.max(axis=0)
            got_lo, got_hi = column_min(a), column_max(a)
            assert got_lo.dtype == want_lo.dtype and got_hi.dtype == want_hi.dtype
            assert np.array_equal(got_lo, want_lo, equal_nan=True) and np.array_equal(got_hi, want_hi, equal_nan=True)


def test_empty_shapes():
    assert finite_rows(np.zeros((0, 3))).shape == (0,)
    assert finite_rows(np.zeros((4, 0))).tolist() == [True] * 4  # no value to fail
    with pytest.raises(ValueError):  # as numpy: no minimum of no rows
        column_min(np.zeros((0, 3)))
