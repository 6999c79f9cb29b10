"""Centre distances in the measurement report carry u from the two fits' centre u."""
import math

import numpy as np

from picms_nodes.measure_report import dimension_table


def _feat(fid, c, u):
    return {"id": fid, "type": "circle", "size": 0.005, "u_size": 1e-7, "center_part": c, "u_center": u,
            "nominal": [0.005]}


def test_distance_u_independent_centres_and_monte_carlo():
    doc = {"features": [_feat("a", [0.0, 0.0], [1e-6, 1e-6]), _feat("b", [0.01, 0.0], [2e-6, 2e-6])],
           "dot_grids": [{"id": "g", "centres_part": [[0.0, 0.005], [0.001, 0.005]]}]}
    rows = {r["name"]: r for r in dimension_table(doc)}
    u = rows["a-b centre distance"]["u"]
    assert math.isclose(u, math.sqrt(5) * 1e-6, rel_tol=1e-12)
    # the same u from sampling the two centres with those sd (isotropic): 20000 draws, ~0.5 % sd
    rng = np.random.default_rng(0)
    a = rng.normal(0, 1e-6, (20000, 2))
    b = np.array([0.01, 0.0]) + rng.normal(0, 2e-6, (20000, 2))
    assert math.isclose(np.std(np.hypot(*(b - a).T)), u, rel_tol=0.03)
    assert rows["a-g centre distance"]["u"] is None      # a dot grid's mean centre has no u
