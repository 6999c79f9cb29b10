import numpy as np
import pytest

from ct_calib_nodes.core.observations import CentreObservations


def _good(q=4):
    return dict(uv_px=np.zeros((q, 2)), sphere_index=np.arange(q), alpha_rad=np.zeros(q),
                view_index=np.zeros(q, int))


def test_valid_and_readonly():
    o = CentreObservations(**_good())
    assert o.n_obs == 4 and o.n_views == 1 and o.n_spheres_seen == 4
    assert o.uv_px.dtype == np.float64 and o.sphere_index.dtype == np.int64
    with pytest.raises(ValueError):
        o.uv_px[0, 0] = 1.0  # read-only


@pytest.mark.parametrize("field, value, word", [
    ("uv_px", np.zeros((4, 3)), "uv_px"),
    ("uv_px", np.array([[np.nan, 0]] * 4), "uv_px"),
    ("sphere_index", np.array([0, 1, -1, 2]), "sphere_index"),
    ("sphere_index", np.array([0, 1.5, 2, 3]), "sphere_index"),
    ("alpha_rad", np.array([0, 0, np.inf, 0]), "alpha_rad"),
    ("view_index", np.zeros(3, int), "view_index"),
    ("sigma_px", np.array([1, 1, 0, 1.0]), "sigma_px"),
    ("stamp_ns", np.array([0.5, 1, 2, 3]), "stamp_ns"),
])
def test_rejects_bad_input(field, value, word):
    kw = _good()
    kw[field] = value
    with pytest.raises(ValueError, match=word):
        CentreObservations(**kw)


def test_from_views_and_select():
    o = CentreObservations.from_views([np.ones((2, 2)), np.zeros((3, 2))], [[0, 1], [2, 3, 4]], [0.0, 0.1],
                                      stamp_ns_per_view=[10, 20])
    assert o.n_obs == 5
    assert list(o.view_index) == [0, 0, 1, 1, 1]
    assert np.allclose(o.alpha_rad, [0, 0, 0.1, 0.1, 0.1])
    assert list(o.stamp_ns) == [10, 10, 20, 20, 20]
    f = o.first_view()
    assert f.n_obs == 2 and list(f.sphere_index) == [0, 1]
    with pytest.raises(ValueError, match="out of range"):
        o.check_spheres(4)
