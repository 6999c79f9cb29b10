"""The detector's sampling helpers, rewritten for speed (issue 14.4), give exactly what the
straightforward formulas give: bilinear interpolation of the frame (``_bilinear``: floor, clip to
the last interior cell, float64 weights), the local background model at image points
(``_background_at``) and the row-wise ``np.interp`` of the edge-spread model (``_interp_rows``),
on random inputs including points on grid nodes, outside the image and outside the table."""

import numpy as np
import pytest

from ct_calib_nodes.core import detect


def _bilinear_reference(img, x, y):
    rows, cols = img.shape
    x0 = np.clip(np.floor(x).astype(np.intp), 0, cols - 2)
    y0 = np.clip(np.floor(y).astype(np.intp), 0, rows - 2)
    fx, fy = x - x0, y - y0
    v00, v01 = img[y0, x0], img[y0, x0 + 1]
    v10, v11 = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    top = v00 + fx * (v01 - v00)
    bot = v10 + fx * (v11 - v10)
    return top + fy * (bot - top)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bilinear_equals_the_reference_formula(seed):
    rng = np.random.default_rng(seed)
    img = rng.normal(1.0, 0.1, (37, 53)).astype(np.float32)
    x = rng.uniform(-1.5, 53.5, (7, 11, 13))
    y = rng.uniform(-1.5, 37.5, (7, 11, 13))
    x[0, 0, :] = np.arange(13)          # grid nodes, the last column, outside on both sides
    y[0, 0, :] = 36.0
    x[1, 0, :3] = (-0.5, 52.0, 53.2)
    got = detect._bilinear(img, x, y)
    assert got.dtype == np.float64 and got.shape == x.shape
    assert np.array_equal(got, _bilinear_reference(img, x, y))


def _background_reference(model, x, y):
    c = x.shape[0]
    sh = (c,) + (1,) * (x.ndim - 1)
    ox, oy = model.origin[:, 0].reshape(sh), model.origin[:, 1].reshape(sh)
    eux, euy = model.eu[:, 0].reshape(sh), model.eu[:, 1].reshape(sh)
    u = (x - ox) * eux + (y - oy) * euy
    v = (x - ox) * (-euy) + (y - oy) * eux
    n = model.a.shape[1]
    fu = np.clip(u - model.umin, 0.0, n - 1.000001)
    i0 = np.floor(fu).astype(np.intp)
    f = fu - i0
    k = np.broadcast_to(np.arange(c).reshape(sh), i0.shape)
    a_u = model.a[k, i0] * (1 - f) + model.a[k, i0 + 1] * f
    b_u = model.b[k, i0] * (1 - f) + model.b[k, i0 + 1] * f
    return a_u + b_u * v, u


@pytest.mark.parametrize("seed", [3, 4])
def test_background_at_equals_the_reference_formula(seed):
    rng = np.random.default_rng(seed)
    c, n = 5, 41
    ang = rng.uniform(0, np.pi, c)
    eu = np.column_stack([np.cos(ang), np.sin(ang)])
    model = detect._LocalBackground(origin=rng.integers(20, 80, (c, 2)).astype(float), eu=eu,
                                    ev=np.column_stack([-eu[:, 1], eu[:, 0]]), umin=-20,
                                    a=rng.normal(1.0, 0.05, (c, n)), b=rng.normal(0.0, 1e-3, (c, n)),
                                    edge_gradient=np.zeros((c, n)), structure=np.ones(c), coherence=np.ones(c),
                                    minor=np.ones(c))
    for shape in ((c, 9), (c, 6, 8)):       # u beyond the grid on both sides included
        x = model.origin[:, 0].reshape((c,) + (1,) * (len(shape) - 1)) + rng.uniform(-30, 30, shape)
        y = model.origin[:, 1].reshape((c,) + (1,) * (len(shape) - 1)) + rng.uniform(-30, 30, shape)
        got, u = detect._background_at(model, x, y)
        want, u_ref = _background_reference(model, x, y)
        assert np.array_equal(got, want) and np.array_equal(u, u_ref)


def test_interp_rows_equals_np_interp_per_row():
    rng = np.random.default_rng(5)
    xp = np.cumsum(rng.uniform(0.01, 0.05, 300)) - 3.0
    fp = rng.normal(size=(17, xp.size)).cumsum(axis=1)
    xq = rng.uniform(xp[0] - 0.5, xp[-1] + 0.5, 17)
    xq[:4] = (xp[0], xp[-1], xp[123], xp[0] - 1.0)       # nodes, both ends, below the table
    got = detect._interp_rows(xq, xp, fp)
    assert np.array_equal(got, np.array([np.interp(q, xp, f) for q, f in zip(xq, fp)]))
