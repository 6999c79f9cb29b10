"""Does one joint fit of all stage positions see a campaign-long focal-spot drift better than the per-position test?

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tests/benchmarks/study_ct_campaign_joint.py [--clean 6] [--seeds 4]

The issue asks for "one joint model of all positions (static + error motions) with campaign-long time terms".
ct_discrepancy.campaign_drift tests the focal spot of each position's own 13-parameter calibration instead. Here
the joint model is fitted directly to every position's centres (feature level, campaign.truth_multi_campaign: 3
positions of 24 projections, 1 h gaps, noise 0.01 px): the 13 static parameters shared, 6 error motions per
further position (started from the first position's static solve and ct's error-motion solve), Gauss-Newton with
central differences of ct_discrepancy.predict_px (its ``motion`` and campaign ``tau``), each position whitened by
its own noise floor (engine Whitener); then the campaign-long focal-spot drift (across the beam: 2 parameters;
along: 1) is tested on that residual as the engine tests a term (delta BIC, 90 % power limit). Printed per
campaign: the per-position test's limit and findings, the joint test's delta chi2, delta BIC, limit and estimate.
Progress on stderr; the last stdout line is one JSON object (limits of both, per campaign).
"""
import argparse
import json
import os
import pathlib
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "ct_discrepancy"))
import numpy as np  # noqa: E402

from campaign import DET, truth_multi_campaign  # noqa: E402
from ct_calib_nodes.core import ct_discrepancy as cd, discrepancy as d  # noqa: E402
from ct_calib_nodes.core.error_motion import solve_error_motion  # noqa: E402
from ct_calib_nodes.core.static_solver import solve_static  # noqa: E402


def _blocked(uv):
    return np.concatenate([uv[:, 0], uv[:, 1]])


class JointModel:
    """Static (13, shared) + error motions (6 per further position) + campaign-long focal-spot drift (3)."""

    def __init__(self, pos, centres, sdd):
        self.pos, self.centres, self.k = pos, centres, len(pos)
        srd0, obs0 = pos[0]
        st0 = solve_static(obs0, centres, DET, srd0, sdd)
        mids = [0.5 * (o.stamp_ns.min() + o.stamp_ns.max()) * 1e-9 for _, o in pos]
        t_mid, span = 0.5 * (max(mids) + min(mids)), max(mids) - min(mids)
        self.taus = [(o.stamp_ns * 1e-9 - t_mid) / span for _, o in pos]
        self.whiten = []
        for srd, obs in pos:                                   # each position's own floor (engine Whitener)
            ds, _ = cd.build_dataset(obs, solve_static(obs, centres, DET, srd, sdd), DET)
            self.whiten.append(d.make_context(ds).wh)
        motions = [np.asarray(solve_error_motion(obs, st0, DET, srd, srd0).x, float) for srd, obs in pos[1:]]
        self.v = np.concatenate([np.asarray(st0.x[:13], float), *motions, np.zeros(3)])
        self.steps = np.concatenate([np.maximum(np.asarray(st0.std[:13]) * 0.1, 1e-9),
                                     np.tile([1e-6] * 3 + [5e-6] * 3, self.k - 1), [2e-6] * 3])

    def predict(self, v, k):
        m = np.zeros(6) if k == 0 else v[13 + 6 * (k - 1):19 + 6 * (k - 1)]
        drift = {"focal_spot_drift": v[-3:-1], "focal_spot_drift_axial": v[-1:]}
        return cd.predict_px(v[:13], self.pos[k][1], self.centres, DET, drift, motion=m, tau=self.taus[k])

    def whitened(self, v):
        """Whitened residual z and design X (columns: static, motions, drift) at v."""
        zs, xs = [], []
        for k in range(self.k):
            obs = self.pos[k][1]
            cols = np.zeros((2 * obs.n_obs, self.v.size))
            for j in range(self.v.size):
                if 13 <= j < self.v.size - 3 and (j - 13) // 6 != k - 1:
                    continue                                   # another position's motion
                up, dn = v.copy(), v.copy()
                up[j] += self.steps[j]
                dn[j] -= self.steps[j]
                cols[:, j] = _blocked(self.predict(up, k) - self.predict(dn, k)) / (2 * self.steps[j])
            zs.append(self.whiten[k](_blocked(obs.uv_px - self.predict(v, k))))
            xs.append(self.whiten[k](cols))
        return np.concatenate(zs), np.vstack(xs)

    def fit_without_drift(self, iterations=3):
        for _ in range(iterations):
            z, x = self.whitened(self.v)
            self.v[:-3] += np.linalg.lstsq(x[:, :-3], z, rcond=None)[0]
        return self.whitened(self.v)


def joint(pos, centres, sdd):
    """Fit the joint model without the drift, then test the drift (across, along the beam) as the engine tests a
    term: {"lat"/"ax": (delta chi2, delta BIC, 90 % limit [um], estimate [um]), "chi2/dof"}."""
    jm = JointModel(pos, centres, sdd)
    z, x = jm.fit_without_drift()
    q0, _ = d._orth(x[:, :-3])
    n = z.size
    zp = d._project_out(q0, z)
    out = {"chi2/dof": float(zp @ zp / (n - q0.shape[1]))}
    for name, idx in (("lat", [0, 1]), ("ax", [2])):
        bp = d._project_out(q0, x[:, [x.shape[1] - 3 + i for i in idx]])
        est = np.linalg.lstsq(bp, zp, rcond=None)[0]
        dchi = float(np.sum((bp @ est) ** 2))
        fisher = bp.T @ bp * 1e-12                             # per um^2
        lam = d.required_noncentrality(len(idx) * np.log(n) + d.BIC_THRESHOLD, len(idx))
        out[name] = (dchi, dchi - len(idx) * np.log(n), float(np.sqrt(lam / np.linalg.eigvalsh(fisher).min())),
                     est * 1e6)
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--clean", type=int, default=6)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--drift", type=float, default=300.0)
    a = ap.parse_args()
    rows = []
    for seed, drift in [(30 + i, 0.0) for i in range(a.clean)] + [(60 + i, a.drift) for i in range(a.seeds)]:
        t0 = time.process_time()
        pos, tr = truth_multi_campaign(seed, n_positions=3, n_views=24, gap_s=3600.0, focal_drift_um=drift,
                                       noise_px=0.01)
        pp = cd.run_positions(pos, tr["ref"].centres_of_m, DET, tr["sdd"])["campaign"]
        t1 = time.process_time()
        j = joint(pos, tr["ref"].centres_of_m, tr["sdd"])
        t2 = time.process_time()
        true = tr["focal_rate_m_per_s"][:2] * pp["span_s"] * 1e6
        row = {"seed": seed, "drift_um": drift, "true_um": true.tolist(),
               "per_position": {"limit_um": pp["detection_limits"]["focal_spot_drift"]["limit"],
                                "named": [(f["term"], f["magnitude"], f["delta_bic"]) for f in pp["findings"]]},
               "joint": {"delta_chi2": j["lat"][0], "delta_bic": j["lat"][1], "limit_um": j["lat"][2],
                         "estimate_um": j["lat"][3].tolist(), "axial": [j["ax"][0], j["ax"][2]],
                         "chi2_dof": j["chi2/dof"]}, "cpu_s": [t1 - t0, t2 - t1]}
        rows.append(row)
        print(json.dumps(row, default=float), file=sys.stderr, flush=True)
    ratio = [r["joint"]["limit_um"] / r["per_position"]["limit_um"] for r in rows]
    print(json.dumps({"campaigns": len(rows), "limit_joint_over_per_position_median": float(np.median(ratio)),
                      "range": [float(min(ratio)), float(max(ratio))],
                      "joint_false_alarms": sum(r["drift_um"] == 0 and r["joint"]["delta_bic"] > 10 for r in rows),
                      "joint_named": sum(r["drift_um"] > 0 and r["joint"]["delta_bic"] > 10 for r in rows),
                      "per_position_named": sum(r["drift_um"] > 0 and bool(r["per_position"]["named"]) for r in rows),
                      "n_drift": a.seeds, "drift_um": a.drift}, default=float))


if __name__ == "__main__":
    main()
