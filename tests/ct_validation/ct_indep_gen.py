"""Independent generator of CT calibration recordings (issue 14 items 1-3).

Written from /work/shared/INTERFACES.md (CT cell: frames, pixel convention, topics, YAML files) and the
seed paper (Ferrucci et al. 2020: eqs 1-2, Appendix A and the seven instrument parameters), with its
own physics. It imports NOTHING from ct_calib_nodes (numpy / scipy / yaml + the shared rosbags writer):

* geometry: point source at the {SRF} origin, rotation axis along +Y through (0, 0, z_R); the object
  (centres from reference_object.yaml, perturbed by their stated CMM uncertainty) placed by eq. 1,
  turned by eq. 2; detector centre D = (x_D, y_D, z_D), axes R_det = Rz(eta) Ry(phi) Rx(theta) applied
  to the ideal detector's (image columns along +X, rows along -Y);
* ray tracing per detector sample: exact chord lengths through steel spheres, a hollow CFRP body tube
  (the spheres sit on it), an optional hollow CFRP support rod at any tilt, an optional PMMA plate;
* a polychromatic beam (three energies: beam hardening) with this module's attenuation values;
* pixel integration: pixel centres inside each holder's outline, then 4 x 4 samples on every sphere's
  shadow box and on every pixel next to a holder edge (a step above 0.002 to a neighbour);
* a detector PSF of its own form: Gaussian core + exponential tail (scatter / glare);
* non-uniform open beam (anode heel gradient + radial fall-off), Poisson counts, Gaussian read noise,
  mono16 counts (or 32FC1 transmission from a flat field measured by averaging open-beam frames).

The truth goes to a file the caller keeps apart from the recording.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import sys

import numpy as np
import yaml
from scipy.signal import fftconvolve

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))     # tests/: the shared writer
from ct_foreign_writer import write_ct_recording  # noqa: E402

DEG = math.pi / 180.0
ROOT = pathlib.Path(__file__).resolve().parents[2]
REFERENCE_OBJECT = ROOT / "ros_ws" / "src" / "ct_calib_nodes" / "config" / "reference_object.yaml"
PARAM_NAMES = ("z_R", "x_D", "y_D", "z_D", "theta", "phi", "eta",
               "x_P", "y_P", "z_P", "rho_X", "rho_Y", "rho_Z")
# Beam: three energy bins (weights of the detected open-beam signal) and this module's attenuation
# coefficients [1/m] per bin: steel, carbon-fibre epoxy, PMMA. Steel ~ 60 / 90 / 130 keV.
BEAM_WEIGHTS = np.array([0.25, 0.45, 0.30])
MU_STEEL = np.array([900.0, 390.0, 200.0])
MU_CFRP = np.array([45.0, 33.0, 28.0])
MU_PMMA = np.array([26.0, 20.0, 17.5])


def rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    if axis == "x":
        return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


@dataclasses.dataclass
class Instrument:
    """The true instrument (paper section 2) and what it reports."""
    w: np.ndarray                  # 13 values in PARAM_NAMES order (instrument + object pose at alpha = 0)
    srd_reported_m: float
    sdd_reported_m: float
    cols: int
    rows: int
    pitch_m: float

    @property
    def r_det(self):
        return rot("z", self.w[6]) @ rot("y", self.w[5]) @ rot("x", self.w[4])

    @property
    def r_obj(self):
        return rot("y", self.w[11]) @ rot("z", self.w[12]) @ rot("x", self.w[10])

    def object_to_srf(self, alpha):
        """(M, t): x_SRF = M x_OF + t at stage angle alpha (eqs 1-2)."""
        ra = rot("y", alpha)
        axis = np.array([0.0, 0.0, self.w[0]])
        return ra @ self.r_obj, axis + ra @ (self.w[7:10] - axis)

    def detector_points(self, col, row):
        """{SRF} positions (N, 3) of image positions (col, row)."""
        cx, cy = (self.cols - 1) / 2.0, (self.rows - 1) / 2.0
        u = (np.asarray(col, float) - cx) * self.pitch_m
        v = (cy - np.asarray(row, float)) * self.pitch_m
        r = self.r_det
        return self.w[1:4] + np.multiply.outer(u, r[:, 0]) + np.multiply.outer(v, r[:, 1])

    def project(self, p_srf):
        """Image positions (N, 2) [col, row] of {SRF} points: the ray from the source meets the detector."""
        p = np.atleast_2d(p_srf)
        r = self.r_det
        n, d = r[:, 2], self.w[1:4]
        x = p * ((n @ d) / (p @ n))[:, None] - d
        cx, cy = (self.cols - 1) / 2.0, (self.rows - 1) / 2.0
        return np.column_stack([cx + x @ r[:, 0] / self.pitch_m, cy - x @ r[:, 1] / self.pitch_m])

    @property
    def principal_point_px(self):
        """Foot of the perpendicular from the source on the detector [col, row]."""
        return self.project(self.r_det[:, 2][None, :])[0]

    def ellipse_centre_px(self, centre_px, semi_minor_px):
        """True centre of a sphere's silhouette ellipse [col, row]: E = P + (1 + (b / D)^2) (C - P),
        C its centre's projection [px], b the shadow's semi-minor axis [px], P the principal point,
        D the source-to-detector distance (ct_calib_nodes doc/ct_core.md)."""
        n = self.r_det[:, 2]
        pp = self.principal_point_px
        return pp + (1 + (semi_minor_px * self.pitch_m / float(n @ self.w[1:4])) ** 2) * (np.asarray(centre_px) - pp)


@dataclasses.dataclass
class Tube:
    """Hollow cylinder in the object frame: axis through `base` along unit `axis`, from s = 0 to `length`."""
    base: np.ndarray
    axis: np.ndarray
    r_out: float
    r_in: float
    length: float

    def chord(self, o, d):
        """Path length in the wall of rays o + t d beyond the source (o (3,), d (N, 3))."""
        e = self.axis
        q0 = o - self.base
        de, qe = d @ e, float(q0 @ e)                     # axial coordinate s(t) = qe + t de in [0, length]
        dp = d - np.outer(de, e)
        qp = q0 - qe * e
        a = np.einsum("ij,ij->i", dp, dp)
        b = dp @ qp
        qq = float(qp @ qp)
        with np.errstate(divide="ignore", invalid="ignore"):
            s1, s2 = -qe / de, (self.length - qe) / de
            inv_a = 1.0 / a
        if 0 <= qe <= self.length:
            lo, hi = np.where(de != 0, np.minimum(s1, s2), -np.inf), np.where(de != 0, np.maximum(s1, s2), np.inf)
        else:
            lo, hi = np.minimum(s1, s2), np.maximum(s1, s2)   # NaN where de == 0: no overlap
        total = np.zeros(d.shape[0])
        for radius, sign in ((self.r_out, 1.0), (self.r_in, -1.0)):
            disc = b * b - a * (qq - radius * radius)
            sq = np.sqrt(np.clip(disc, 0.0, None))
            t_lo = np.maximum((-b - sq) * inv_a, lo)
            t_hi = np.minimum((-b + sq) * inv_a, hi)
            seg = np.where(disc > 0, t_hi - t_lo, 0.0)
            total += sign * np.nan_to_num(np.clip(seg, 0.0, None))
        return total * np.sqrt(np.einsum("ij,ij->i", d, d))

    def outline(self):
        """Points (n, 3) whose convex hull contains the tube (its end circles, with a margin)."""
        e = self.axis
        u = np.cross(e, [0.0, 0.0, 1.0] if abs(e[2]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(e, u)
        ang = np.linspace(0, 2 * math.pi, 48, endpoint=False)
        ring = 1.05 * self.r_out * (np.outer(np.cos(ang), u) + np.outer(np.sin(ang), v))
        return np.vstack([self.base + ring, self.base + self.length * e + ring])


@dataclasses.dataclass
class Plate:
    """Axis-aligned box in the object frame."""
    lo: np.ndarray
    hi: np.ndarray

    def chord(self, o, d):
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (self.lo - o) / d
            t2 = (self.hi - o) / d
        t1 = np.where(d == 0, np.where((o >= self.lo) & (o <= self.hi), -np.inf, np.inf), t1)
        t2 = np.where(d == 0, np.where((o >= self.lo) & (o <= self.hi), np.inf, -np.inf), t2)
        t_lo = np.max(np.minimum(t1, t2), axis=1)
        t_hi = np.min(np.maximum(t1, t2), axis=1)
        return np.clip(t_hi - t_lo, 0.0, None) * np.sqrt(np.einsum("ij,ij->i", d, d))

    def outline(self):
        return np.array([[x, y, z] for x in (self.lo[0], self.hi[0]) for y in (self.lo[1], self.hi[1])
                         for z in (self.lo[2], self.hi[2])])


@dataclasses.dataclass
class Physics:
    counts: float = 40000.0         # mean open-beam counts
    heel: float = 0.1               # relative gain gradient across the field (anode heel)
    heel_dir: float = 0.0           # its direction in the image [rad]
    falloff: float = 0.1            # relative gain loss at the field corners
    read_sd: float = 8.0            # read noise [counts]
    psf_sigma_px: float = 0.6       # Gaussian core
    tail_fraction: float = 0.04     # share of the signal in the exponential tail
    tail_scale_px: float = 6.0
    encoding: str = "mono16"        # or "32FC1"
    tube: bool = True
    rod_tilt_deg: float | None = None   # support rod under the object (None = no rod)
    plate: bool = False

    def to_dict(self):
        return dataclasses.asdict(self)


def load_reference(path=REFERENCE_OBJECT):
    """(ids, centres (N, 3), diameters (N,), centre uncertainties (N,)) from a reference_object.yaml."""
    doc = yaml.safe_load(pathlib.Path(path).read_text())
    sph = doc["spheres"]
    return (np.array([s["id"] for s in sph]), np.array([s["center"] for s in sph], float),
            np.array([s["diameter"] for s in sph], float), np.array([s.get("center_uncertainty", 0.0) for s in sph]))


def holders(phys: Physics, centres_of, diameters):
    """The support structures in the object frame: (tubes, plates) and the attenuation of each."""
    r_s = np.hypot(centres_of[:, 0], centres_of[:, 2]).mean() - diameters.mean() / 2
    y0, y1 = centres_of[:, 1].min() - 0.008, centres_of[:, 1].max() + 0.008
    parts = []
    if phys.tube:
        parts.append((Tube(np.array([0.0, y0, 0.0]), np.array([0.0, 1.0, 0.0]), r_s, r_s - 0.0012, y1 - y0), MU_CFRP))
    if phys.rod_tilt_deg is not None:                 # from below the object, tilted towards +X
        tilt = phys.rod_tilt_deg * DEG
        axis = np.array([math.sin(tilt), math.cos(tilt), 0.0])
        parts.append((Tube(np.array([0.0, y0, 0.0]) - 0.06 * axis, axis, 0.005, 0.0035, 0.06), MU_CFRP))
    if phys.plate:
        parts.append((Plate(np.array([-0.05, y0 - 0.01, -0.05]), np.array([0.05, y0 - 0.004, 0.05])), MU_PMMA))
    return parts


def _shadow_radius_px(inst, c_srf, radius):
    """Upper bound of a sphere's shadow half-size on the detector [px]."""
    dist = np.linalg.norm(c_srf, axis=1)
    half_angle = np.arcsin(np.clip(radius / dist, 0, 0.5))
    n = inst.r_det[:, 2]
    cos_off = np.abs(c_srf @ n) / dist
    depth = n @ inst.w[1:4]
    return depth * np.tan(half_angle) / cos_off ** 2 / inst.pitch_m


def _gain(inst, phys):
    r, c = np.mgrid[0 : inst.rows, 0 : inst.cols].astype(float)
    xn = (c - (inst.cols - 1) / 2) / (inst.cols / 2)
    yn = ((inst.rows - 1) / 2 - r) / (inst.rows / 2)
    g = 1.0 + phys.heel * (xn * math.cos(phys.heel_dir) + yn * math.sin(phys.heel_dir))
    return g * (1.0 - phys.falloff * (xn * xn + yn * yn) / 2)


def _psf_kernel(phys):
    half = int(math.ceil(max(4 * phys.psf_sigma_px, 5 * phys.tail_scale_px if phys.tail_fraction else 0, 2)))
    y, x = np.mgrid[-half : half + 1, -half : half + 1].astype(float)
    rr = np.hypot(x, y)
    core = np.exp(-0.5 * (rr / phys.psf_sigma_px) ** 2)
    k = (1 - phys.tail_fraction) * core / core.sum()
    if phys.tail_fraction:
        tail = np.exp(-rr / phys.tail_scale_px)
        k = k + phys.tail_fraction * tail / tail.sum()
    return k


class Renderer:
    def __init__(self, inst: Instrument, centres_of, diameters, phys: Physics):
        self.inst, self.phys = inst, phys
        self.centres_of, self.radii = np.asarray(centres_of, float), np.asarray(diameters, float) / 2
        self.parts = holders(phys, self.centres_of, np.asarray(diameters, float))
        self.gain = _gain(inst, phys)
        self.kernel = _psf_kernel(phys)

    def sphere_centres(self, alpha):
        m, t = self.inst.object_to_srf(alpha)
        return self.centres_of @ m.T + t

    def _transmission(self, col, row, alpha, spheres=()):
        """Polychromatic transmission of the rays to image positions (col, row) (1-D arrays).

        ``spheres``: (sphere index, sample indices) pairs: the samples whose ray may cross that sphere."""
        inst = self.inst
        d = inst.detector_points(col, row)                     # rays from the source (origin) to the detector
        m, t = inst.object_to_srf(alpha)
        o_of, d_of = -(m.T @ t), d @ m                        # the same rays in the object frame
        line = np.zeros((col.size, 3))                        # mu-weighted path per energy bin
        for part, mu in self.parts:
            line += np.multiply.outer(part.chord(o_of, d_of), mu)
        if len(spheres):
            c_srf = m @ self.centres_of.T + t[:, None]
            for k, sel in spheres:
                c = c_srf[:, k]
                ds = d[sel]
                dc = ds @ c
                perp2 = c @ c - dc * dc / np.einsum("ij,ij->i", ds, ds)
                chord = 2 * np.sqrt(np.clip(self.radii[k] ** 2 - perp2, 0, None))
                line[sel] += np.multiply.outer(chord, MU_STEEL)
        return np.exp(-line) @ BEAM_WEIGHTS

    def transmission_image(self, alpha, n_fine=4):
        """Noise-free, PSF-free pixel-integrated transmission, sphere centre projections, shadow radius bounds.

        Pixel centres first (holders only); then every pixel of a sphere shadow's box and every pixel
        next to a holder edge (a step above 0.002 to a neighbour) is integrated on n_fine x n_fine samples."""
        inst = self.inst
        c_srf = self.sphere_centres(alpha)
        cr, rad = inst.project(c_srf), _shadow_radius_px(inst, c_srf, self.radii)
        rr, cc = np.mgrid[0 : inst.rows, 0 : inst.cols]
        img = np.ones(rr.shape)
        m, t = inst.object_to_srf(alpha)
        for part, _ in self.parts:                             # pixel centres inside each holder's outline
            uv = inst.project(part.outline() @ m.T + t)
            c0, r0 = np.clip(np.floor(uv.min(axis=0)) - 2, 0, None).astype(int)
            c1, r1 = np.ceil(uv.max(axis=0)).astype(int) + 3
            if c1 > c0 and r1 > r0:
                win = (slice(r0, r1), slice(c0, c1))
                img[win] = self._transmission(cc[win].ravel().astype(float), rr[win].ravel().astype(float),
                                              alpha).reshape(rr[win].shape)
        edge = np.zeros(img.shape, bool)
        step_c = np.abs(np.diff(img, axis=1)) > 0.002
        step_r = np.abs(np.diff(img, axis=0)) > 0.002
        edge[:, 1:] |= step_c
        edge[:, :-1] |= step_c
        edge[1:, :] |= step_r
        edge[:-1, :] |= step_r
        boxes = []
        for k in range(len(cr)):
            h = rad[k] + 1.5
            c0, c1 = max(int(cr[k, 0] - h), 0), min(int(cr[k, 0] + h) + 1, inst.cols - 1)
            r0, r1 = max(int(cr[k, 1] - h), 0), min(int(cr[k, 1] + h) + 1, inst.rows - 1)
            if c0 <= c1 and r0 <= r1:
                edge[r0 : r1 + 1, c0 : c1 + 1] = True
                boxes.append((k, r0, r1, c0, c1))
        pos = np.full(img.shape, -1)
        idx = np.flatnonzero(edge)
        pos.ravel()[idx] = np.arange(idx.size)
        n2 = n_fine * n_fine
        spheres = []
        for k, r0, r1, c0, c1 in boxes:
            p = pos[r0 : r1 + 1, c0 : c1 + 1].ravel()
            spheres.append((k, (p[:, None] * n2 + np.arange(n2)).ravel()))
        off = (np.arange(n_fine) + 0.5) / n_fine - 0.5
        oc, orr = np.meshgrid(off, off)
        col = (cc.ravel()[idx][:, None] + oc.ravel()).ravel()
        row = (rr.ravel()[idx][:, None] + orr.ravel()).ravel()
        img.ravel()[idx] = self._transmission(col, row, alpha, spheres).reshape(-1, n2).mean(axis=1)
        return img, cr, rad

    def frame(self, alpha, rng):
        """(image as recorded, sphere centre projections (N, 2), shadow radii bound (N,))."""
        tr, cr, rad = self.transmission_image(alpha)
        k = self.kernel
        h = k.shape[0] // 2
        blurred = fftconvolve(np.pad(tr, h, mode="edge"), k, mode="valid")
        phys = self.phys
        mean = phys.counts * self.gain * blurred
        counts = rng.poisson(mean).astype(float) + rng.normal(0.0, phys.read_sd, mean.shape)
        counts = np.clip(np.rint(counts), 0, 65535)
        if phys.encoding == "mono16":
            return counts.astype(np.uint16), cr, rad
        # 32FC1: flat-field corrected with an open-beam reference averaged over 16 frames
        flat = rng.poisson(phys.counts * self.gain * 16).astype(float) / 16
        return (counts / flat).astype(np.float32), cr, rad


def shadow_clearance(inst, cr, rad, *, margin_px=2.0):
    """Per sphere: the gap [px] between its shadow and the nearest other shadow (radius upper bounds, so
    the true gap is at least this), -inf where the shadow is not inside the detector with `margin_px`."""
    inside = ((cr[:, 0] - rad > margin_px) & (cr[:, 0] + rad < inst.cols - 1 - margin_px)
              & (cr[:, 1] - rad > margin_px) & (cr[:, 1] + rad < inst.rows - 1 - margin_px))
    gap = np.linalg.norm(cr[:, None, :] - cr[None, :, :], axis=2) - rad[:, None] - rad[None, :]
    np.fill_diagonal(gap, np.inf)
    return np.where(inside, gap.min(axis=1), -np.inf)


def draw_case(seed: int, *, cols=512, n_views=36, vary_physics=True, object_tilt_deg=0.5):
    """A random instrument, object pose, CMM error and physics (all from `seed`).

    ``object_tilt_deg``: the object (and its body tube) leans off the rotation axis by up to this much
    about X and Z each (rho_X, rho_Z)."""
    rng = np.random.default_rng(seed)
    ids, c_file, diam, u_c = load_reference()
    srd = rng.uniform(0.30, 0.70)
    sdd = 1.0 + rng.uniform(0.0, 0.3)
    z_r = srd + rng.uniform(-2e-3, 2e-3)                     # the reported SRD is off by up to 2 mm
    w = np.array([z_r, rng.uniform(-4e-3, 4e-3), rng.uniform(-4e-3, 4e-3), sdd + rng.uniform(-4e-3, 4e-3),
                  *(rng.uniform(-0.6, 0.6, 3) * DEG),
                  rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), z_r + rng.uniform(-1e-3, 1e-3),
                  0.0, rng.uniform(0, 2 * math.pi), 0.0])
    w[10], w[12] = rng.uniform(-1, 1, 2) * object_tilt_deg * DEG
    extent = np.max(np.linalg.norm(c_file, axis=1)) + 0.004
    mag = sdd / (z_r - extent)                               # worst case: the nearest sphere
    pitch = round(2 * 1.08 * extent * mag / cols, 6)         # the object's projection fills the detector
    inst = Instrument(w, srd, sdd, cols, cols, pitch)
    if vary_physics:
        phys = Physics(counts=rng.uniform(12000, 55000), heel=rng.uniform(0, 0.2), heel_dir=rng.uniform(0, 2 * math.pi),
                       falloff=rng.uniform(0, 0.3), read_sd=rng.uniform(2, 25), psf_sigma_px=rng.uniform(0.3, 1.1),
                       tail_fraction=rng.uniform(0, 0.08), tail_scale_px=rng.uniform(3, 15),
                       encoding="32FC1" if rng.random() < 0.25 else "mono16", tube=rng.random() < 0.8,
                       rod_tilt_deg=float(rng.uniform(-60, 60)) if rng.random() < 0.4 else None,
                       plate=rng.random() < 0.25)
    else:
        phys = Physics()
    c_true = c_file + rng.normal(0.0, 1.0, c_file.shape) * u_c[:, None]      # CMM errors within their u
    alphas = np.linspace(0, 2 * math.pi, n_views, endpoint=False) + rng.uniform(0, 2 * math.pi / n_views)
    return dict(seed=seed, ids=ids, c_file=c_file, c_true=c_true, diam=diam, u_c=u_c, inst=inst, phys=phys,
                alphas=alphas, rng=rng)


def generate(rec_dir, truth_path, seed: int, **kw):
    """Render a recording into `rec_dir` (+ its YAML files) and the truth into `truth_path` (apart)."""
    case = draw_case(seed, **kw)
    inst, phys, rng = case["inst"], case["phys"], case["rng"]
    ren = Renderer(inst, case["c_true"], case["diam"], phys)
    rec_dir = pathlib.Path(rec_dir)
    rec_dir.parent.mkdir(parents=True, exist_ok=True)
    views = []
    t0 = 1_760_000_000_000_000_000 + seed * 10**12

    def frames():
        for j, a in enumerate(case["alphas"]):
            img, cr, rad = ren.frame(a, rng)
            views.append({"alpha": float(a), "centre_px": cr.tolist(), "shadow_radius_px": rad.tolist(),
                          "gap_px": shadow_clearance(inst, cr, rad).tolist()})
            # the stage read-back of the magnification axis jitters by a few um
            yield t0 + j * 400_000_000, img, a, inst.srd_reported_m + rng.normal(0, 2e-6)

    write_ct_recording(rec_dir, frames())
    (rec_dir / "ct_instrument.yaml").write_text(yaml.safe_dump({
        "units": "SI", "source_to_detector": float(inst.sdd_reported_m),
        "detector": {"cols": inst.cols, "rows": inst.rows, "pixel_pitch": float(inst.pitch_m),
                     "flat_field_counts": float(round(phys.counts * ren.gain.mean()))}}, sort_keys=False))
    (rec_dir / "reference_object.yaml").write_text(REFERENCE_OBJECT.read_text())    # as the user has it
    truth = {"warning": "simulation truth: never an input of a solver", "seed": seed,
             "param_names": list(PARAM_NAMES), "w": inst.w.tolist(), "srd_reported_m": inst.srd_reported_m,
             "sdd_reported_m": inst.sdd_reported_m, "cols": inst.cols, "rows": inst.rows, "pitch_m": inst.pitch_m,
             "ids": case["ids"].tolist(), "centres_true_of_m": case["c_true"].tolist(), "physics": phys.to_dict(),
             "views": views}
    pathlib.Path(truth_path).parent.mkdir(parents=True, exist_ok=True)
    pathlib.Path(truth_path).write_text(json.dumps(truth))
    return truth


def instrument_from(w, truth) -> Instrument:
    """An Instrument with parameters w (13) and the truth file's detector."""
    return Instrument(np.asarray(w, float), truth["srd_reported_m"], truth["sdd_reported_m"], truth["cols"],
                      truth["rows"], truth["pitch_m"])


def predicted_px(w, centres_of, alphas, truth):
    """Sphere centre projections (n_views, N, 2) under parameters w: this module's projection, eqs 1-2 + App. A."""
    inst = instrument_from(w, truth)
    out = []
    for a in alphas:
        m, t = inst.object_to_srf(a)
        out.append(inst.project(np.asarray(centres_of) @ m.T + t))
    return np.array(out)


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording_dir")
    ap.add_argument("truth_json", help="keep it apart from the recording")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cols", type=int, default=512)
    ap.add_argument("--views", type=int, default=36)
    a = ap.parse_args()
    generate(a.recording_dir, a.truth_json, a.seed, cols=a.cols, n_views=a.views)
