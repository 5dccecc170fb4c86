import numpy as np


def xs(*vals):
    """Points on the x axis."""
    v = np.asarray(vals, dtype=np.float64).reshape(-1)
    return np.c_[v, np.zeros_like(v), np.zeros_like(v)]


def xrange_pts(a, b):
    return xs(*np.arange(a, b))
