"""Does a smooth gain gradient across the frame move the detected sphere centres? (issue 14.2, study; not a test)

The detector corrects each edge point for the blur of the product shadow x background (``_edge_points``:
``r += spread^2 d ln B / dr``), which is right when the background's variation lies in the beam before the
detector's blur (a holder's wall, the anode heel's fluence) and wrong when it is a gain applied after the
blur (a detector gain map, what ct_indep_gen.py and core/holders.py FlatField render): then the correction
itself moves every centre by ``spread^2 grad ln g`` towards the higher gain. One frame cannot tell the two
apart. This measures the shift on noise-free frames of ct_indep_gen (its renderer, not the project's):
the same instrument, object and views rendered with no gain gradient and with a heel of ``--heel`` along
the columns and along the rows (Poisson and read noise off, counts rounded, no PSF tail, no fall-off),
detected as the offline solver detects raw mono16 frames, centres paired by nearest true projection.

    .venv/bin/python tests/benchmarks/study_ct_gain_gradient_shift.py --seeds 7227,7224 [--views 6] [--heel 0.2]
    .venv/bin/python tests/benchmarks/study_ct_gain_gradient_shift.py --noisy --seeds 7231,7247 --views 36

``--noisy``: each recording's own physics (counts, read noise, PSF tail, fall-off) and heel as drawn, heel
on against off under one fixed noise field per view (Gaussian for Poisson), so the pair differs by the
heel alone: median and mean change and the centres that change by more than 0.003 px.

Since round 27 the detector corrects only half of the frame-wide smooth part (DetectionSettings.
``frame_gradient_share``, the rest reported as a shared systematic): ``--set frame_gradient_share=1``
gives the round-26 behaviour these figures were first measured with.

Prints per seed and direction the mean and median shift (cols, rows) against ``spread^2 grad ln g`` (the renderer's
PSF sd squared plus 1/12 for the pixel aperture), then ONE JSON line. Measured figures: ct_detect.md,
"A gain gradient applied after the blur".
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent / "ct_validation")]

import ct_indep_gen as gen  # noqa: E402
from ct_calib_nodes.core.detect import DetectionSettings, detect_spheres  # noqa: E402

COUNTS = 50000.0


class _NoNoise:
    """Stands in for the generator's random stream: the mean counts, no read noise."""

    @staticmethod
    def poisson(lam):
        return np.asarray(lam, float)

    @staticmethod
    def normal(mean, sd, shape):
        return np.zeros(shape)


class _FixedNoise:
    """One noise field per view for every rendering of it: counts lam + sqrt(lam) z1 (Gaussian for
    Poisson), read noise sd z2, so two renderings of a view differ by their means only."""

    def __init__(self, seed, shape):
        g = np.random.default_rng(seed)
        self.z1, self.z2 = g.standard_normal(shape), g.standard_normal(shape)

    def poisson(self, lam):
        return lam + np.sqrt(lam) * self.z1

    def normal(self, mean, sd, shape):
        return mean + sd * self.z2


def centres(case, views, settings, noise=False):
    """{(view, true sphere index): detected centre (col, row)}."""
    inst = case["inst"]
    ren = gen.Renderer(inst, case["c_true"], case["diam"], case["phys"])
    out = {}
    for j, a in enumerate(case["alphas"][:views]):
        rng = _FixedNoise(1000 + j, (inst.rows, inst.cols)) if noise else _NoNoise()
        img, cr, _ = ren.frame(a, rng)
        det = detect_spheres(img, encoding="mono16", flat_field_counts=case["phys"].counts, settings=settings)
        for c in det.centre_px:
            d = np.linalg.norm(cr - c, axis=1)
            out[(j, int(np.argmin(d)))] = np.asarray(c, float)
    return out


def _change(ref, got):
    """(M, 2) centre changes got - ref over the (view, sphere) pairs found in both."""
    return np.array([got[k] - ref[k] for k in got if k in ref])


def _predicted(phys, heel, heel_dir, cols):
    """spread^2 grad ln g at the frame's centre (cols, rows) [px]: the renderer's PSF sd squared plus
    1/12 for the pixel aperture; the gain rises towards +col (heel_dir 0) or the top, -row (pi/2)."""
    spread2 = phys.psf_sigma_px ** 2 + 1.0 / 12.0
    return spread2 * heel / (cols / 2) * np.array([math.cos(heel_dir), -math.sin(heel_dir)]) + 0.0   # no -0.0


def study_noisy(seed, views, settings):
    """The recording's own physics (counts, read noise, tail, fall-off, heel as drawn; mono16), heel on
    against heel off under one fixed noise field per view: the median and mean change, and the centres
    that change by more than 0.003 px."""
    case = gen.draw_case(seed)
    ph = case["phys"]
    ph.encoding = "mono16"
    heel = ph.heel
    ph.heel = 0.0
    ref = centres(case, views, settings, noise=True)
    ph.heel = heel
    d = _change(ref, centres(case, views, settings, noise=True))
    big = np.abs(d).max(axis=1) > 0.003
    pred = _predicted(ph, heel, ph.heel_dir, case["inst"].cols)
    row = {"seed": seed, "tube": bool(ph.tube), "heel": round(heel, 3), "heel_dir": round(ph.heel_dir, 3),
           "counts": round(ph.counts), "n": len(d), "predicted_px": np.round(pred, 6).tolist(),
           "median_change_px": np.round(np.median(d, 0), 6).tolist(), "mean_change_px": np.round(d.mean(0), 6).tolist(),
           "se_mean_px": np.round(d.std(0) / np.sqrt(len(d)), 6).tolist(), "n_over_3e-3": int(big.sum()),
           "mean_change_of_those_px": np.round(d[big].mean(0), 5).tolist() if big.any() else None}
    print(f"seed {seed} (noise as drawn, heel {heel:.3f} at {ph.heel_dir:.2f} rad): {len(d)} centres, change median "
          f"{row['median_change_px']} mean {row['mean_change_px']} (se {row['se_mean_px']}) px, predicted {row['predicted_px']}; "
          f"{row['n_over_3e-3']} change by > 0.003 px, their mean {row['mean_change_of_those_px']}", flush=True)
    return row


def study(seed, views, heel, settings):
    case = gen.draw_case(seed)
    ph = case["phys"]
    ph.counts, ph.read_sd, ph.tail_fraction, ph.falloff, ph.encoding = COUNTS, 0.0, 0.0, 0.0, "mono16"
    ph.heel = 0.0
    ref = centres(case, views, settings)
    row = {"seed": seed, "tube": bool(ph.tube), "psf_sigma_px": round(ph.psf_sigma_px, 3), "heel": heel,
           "cols": case["inst"].cols}
    for label, direction in (("cols", 0.0), ("rows", 0.5 * math.pi)):
        ph.heel, ph.heel_dir = heel, direction
        d = _change(ref, centres(case, views, settings))
        pred = _predicted(ph, heel, direction, case["inst"].cols)
        row[label] = {"n": len(d), "mean_shift_px": np.round(d.mean(0), 6).tolist(),
                      "median_shift_px": np.round(np.median(d, 0), 6).tolist(),
                      "sd_px": np.round(d.std(0), 6).tolist(), "predicted_px": np.round(pred, 6).tolist()}
        print(f"seed {seed} tube {ph.tube!s:5s} psf {ph.psf_sigma_px:.2f} px, heel {heel} along {label}: "
              f"{len(d)} centres, shift mean {np.round(d.mean(0), 5)} median {np.round(np.median(d, 0), 5)} px "
              f"(sd {np.round(d.std(0), 5)}), "
              f"spread^2 grad ln g {np.round(pred, 5)}", flush=True)
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="7227,7224", help="comma-separated ct_indep_gen seeds")
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--heel", type=float, default=0.2, help="relative gain change from the centre to an edge")
    ap.add_argument("--noisy", action="store_true",
                    help="instead: each recording's own physics and heel, with one fixed noise field per view")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a DetectionSettings field (float), e.g. edge_spread_px=0")
    args = ap.parse_args()
    settings = DetectionSettings(**{k: float(v) for k, v in (a.split("=", 1) for a in args.set)})
    if args.noisy:
        rows = [study_noisy(int(s), args.views, settings) for s in args.seeds.split(",")]
    else:
        rows = [study(int(s), args.views, args.heel, settings) for s in args.seeds.split(",")]
    print(json.dumps({"heel": args.heel, "views": args.views, "noisy": args.noisy, "cases": rows}))


if __name__ == "__main__":
    main()
