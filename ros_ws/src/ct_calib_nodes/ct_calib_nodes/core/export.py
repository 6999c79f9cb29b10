"""Export of a calibrated CT geometry for tomographic reconstruction.

The calibration (geometry.py, Ferrucci et al. 2020 eqs 4-11) describes each
stage position k by the k = 1 geometry in the detector frame {DF} plus six
error motions. A reconstruction package wants, for every projection (stage
position k, rotary angle alpha), where the source and the detector pixels are
relative to a volume that turns with the object. This module gives that in
two forms, both derived from the same rigid transforms:

* 3x4 projection matrices P (pinhole style): ``[col, row, 1] ~ P @ [x, y, z, 1]``
  with (x, y, z) a point of the reconstruction volume frame {VF} in metres
  and (col, row) image coordinates in the OpenCV convention of
  ``geometry.DetectorSpec`` (pixel (c, r) centred at (c, r)).
* ASTRA Toolbox ``cone_vec`` rows ``(srcX, srcY, srcZ, dX, dY, dZ, uX, uY,
  uZ, vX, vY, vZ)``.

Reconstruction volume frame {VF} of stage position k
---------------------------------------------------
{VF} is rigidly attached to the object (it turns with the rotary table), so a
reconstruction expressed in it is the same for every view. At alpha = 0:

* origin: the stage point R_k (eq. 8), i.e. the point where the source ->
  rotation-axis perpendicular meets the rotation axis at k = 1, carried by the
  error motions of position k: ``R_k = R_1 + (dx_R, dy_R, dz_R)`` in {DF};
* +Y_VF: the rotation axis r_k (eq. 9), ``r_k = Rot(gamma_k) r_1``;
* +Z_VF: from R_k toward the source S, projected perpendicular to r_k and
  normalised (for the aligned instrument this is -Z_SRF);
* +X_VF = Y_VF x Z_VF (right-handed).

At angle alpha the object, and {VF} with it, is turned by +alpha about r_k
through R_k: ``T_df_from_vf(alpha) = T(R_k) Rot(r_k, alpha) B_k`` with B_k the
alpha = 0 axes above. All lengths are in metres.

The object frame {OF} of the reference object maps into {VF} by the fixed
transform ``T_vf_from_of`` (see :func:`volume_frame_from_object`), so sphere
centres from the CMM certificate can be projected with P directly.

ASTRA conventions used by :func:`astra_cone_vec`
------------------------------------------------
ASTRA (docs/geom3d.rst of astra-toolbox.github.io; backend
CConeVecProjectionGeometry3D) takes, per projection, the source ``src``, the
detector centre ``d``, ``u`` = vector from detector pixel (0, 0) to (0, 1)
(next *column*) and ``v`` = vector from pixel (0, 0) to (1, 0) (next *row*);
pixel (row r, col c) is centred at ``d + (c - (cols-1)/2) u + (r - (rows-1)/2) v``.
The projection data array is ``proj[row, view, col]``; the volume array is
``vol[z, y, x]`` with voxel centres at ``(i - n/2 + 0.5) * voxel`` about the
volume centre (``create_vol_geom(n_y_rows, n_x_cols, n_z_slices)``).
Axes: ``X_astra = X_VF``, ``Y_astra = -Z_VF``, ``Z_astra = Y_VF`` (right-handed;
the rotation axis is ASTRA Z, the source at alpha = 0 sits on ASTRA -Y as in
ASTRA's own ``cone`` geometry). Rows of the recorded images are NOT flipped:
``v`` points down the image (row 0 on top), so ``proj[r, j, c]`` is simply
``image_j[r, c]``. Lengths are divided by ``length_unit_m``: pass the voxel
size to use ASTRA's default unit-voxel volume centred on R_k, or 1e-3 to work
in millimetres with ``create_vol_geom(..., min_x, max_x, ...)`` in mm.

TIGRE
-----
Not exported. TIGRE's geometry (DSD, DSO, offOrigin, offDetector,
rotDetector, angles as ZYZ Euler triples) can hold per-view values, but its
sign and composition conventions for rotDetector (roll/pitch/yaw about the
detector centre) and offDetector could not be checked here without running
TIGRE; a wrong convention would silently mis-reconstruct. The cone_vec rows
carry all the information (source, detector centre, u, v per view) needed to
build it once those conventions are pinned by a test against TIGRE itself.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from .geometry import (
    MOTION_PARAM_NAMES,
    _check_motion,
    DetectorFrameGeometry,
    DetectorSpec,
    detector_rotation,
    motion_rotation,
    object_rotation,
    rot_axis_angle,
)

__all__ = [
    "T_ASTRA_FROM_VF",
    "volume_frame_pose",
    "T_df_from_vf",
    "T_df1_from_of",
    "volume_frame_from_object",
    "projection_matrices",
    "project_with_matrices",
    "astra_cone_vec",
    "export_geometry_files",
]

#: Rotation (3, 3) from {VF} axes to ASTRA volume axes: X_a = X_vf, Y_a = -Z_vf, Z_a = Y_vf.
T_ASTRA_FROM_VF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


# ----------------------------------------------------------------------------- checks

def _check_geom(geom) -> DetectorFrameGeometry:
    if not isinstance(geom, DetectorFrameGeometry):
        raise ValueError(f"geom must be a geometry.DetectorFrameGeometry, got {type(geom).__name__}")
    for name in ("source_df_m", "stage_df_m", "axis_df"):
        a = np.asarray(getattr(geom, name), dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"geom.{name} must be 3 finite values, got shape {a.shape}")
    n = np.linalg.norm(np.asarray(geom.axis_df, dtype=float))
    if not abs(n - 1.0) < 1e-9:
        raise ValueError(f"geom.axis_df must be a unit vector, its norm is {n}")
    if not float(geom.source_df_m[2]) < 0.0:
        raise ValueError("geom.source_df_m must lie on the -Z side of the detector (z < 0)")
    return geom


def _check_alpha(alpha_rad) -> np.ndarray:
    a = np.atleast_1d(np.asarray(alpha_rad, dtype=float))
    if a.ndim != 1 or a.size == 0:
        raise ValueError(f"alpha_rad must have shape (M,) with M >= 1, got {np.shape(alpha_rad)}")
    if not np.all(np.isfinite(a)):
        raise ValueError("alpha_rad contains NaN or inf")
    return a


def _check_detector(detector) -> DetectorSpec:
    if not isinstance(detector, DetectorSpec):
        raise ValueError(f"detector must be a geometry.DetectorSpec, got {type(detector).__name__}")
    return detector


def _check_T(T, name) -> np.ndarray:
    t = np.asarray(T, dtype=float)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise ValueError(f"{name} must be a finite (4, 4) homogeneous transform, got shape {t.shape}")
    r = t[:3, :3]
    if not (np.allclose(r.T @ r, np.eye(3), atol=1e-9) and np.allclose(t[3], [0, 0, 0, 1])
            and np.linalg.det(r) > 0):
        raise ValueError(f"{name} must be a proper rigid transform (orthonormal rotation, last row 0 0 0 1)")
    return t


def _homogeneous(rot, trans) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = trans
    return t


# ----------------------------------------------------------------------------- frames

def volume_frame_pose(geom: DetectorFrameGeometry, motion) -> np.ndarray:
    """Pose of {VF} in {DF} at alpha = 0 for one stage position.

    Parameters
    ----------
    geom : geometry.DetectorFrameGeometry
        The k = 1 geometry in {DF}.
    motion : array_like of shape (6,)
        Error motions of position k relative to k = 1: dx_R, dy_R, dz_R [m],
        gamma_X, gamma_Y, gamma_Z [rad] (zeros for k = 1).

    Returns
    -------
    ndarray of shape (4, 4)
        ``T_df_from_vf0``: columns 0-2 of the rotation are X_VF, Y_VF, Z_VF
        in {DF}; the translation is R_k [m].
    """
    geom = _check_geom(geom)
    m = _check_motion(motion)
    g = motion_rotation(m[3], m[4], m[5])
    r_k = np.asarray(geom.stage_df_m, dtype=float) + m[:3]          # eq. 8
    y = g @ np.asarray(geom.axis_df, dtype=float)                   # eq. 9
    y = y / np.linalg.norm(y)
    to_src = np.asarray(geom.source_df_m, dtype=float) - r_k
    z = to_src - (to_src @ y) * y
    nz = np.linalg.norm(z)
    if nz < 1e-9:
        raise ValueError("the rotation axis passes through the source; {VF} is undefined")
    z = z / nz
    x = np.cross(y, z)
    return _homogeneous(np.stack([x, y, z], axis=1), r_k)


def T_df_from_vf(geom: DetectorFrameGeometry, motion, alpha_rad) -> np.ndarray:
    """Pose of {VF} in {DF} at each rotary angle (the object turned by +alpha).

    Parameters
    ----------
    geom : geometry.DetectorFrameGeometry
    motion : array_like of shape (6,)
    alpha_rad : array_like of shape (M,)
        Rotary angles [rad].

    Returns
    -------
    ndarray of shape (M, 4, 4)
        ``T_df_from_vf[j] = T(R_k) Rot(r_k, alpha_j) T(-R_k) T_df_from_vf0``.
    """
    t0 = volume_frame_pose(geom, motion)
    a = _check_alpha(alpha_rad)
    y = t0[:3, 1]
    rot = rot_axis_angle(y, a)                                      # (M, 3, 3)
    out = np.zeros((a.size, 4, 4))
    out[:, :3, :3] = rot @ t0[:3, :3]
    out[:, :3, 3] = t0[:3, 3]                                       # R_k is on the axis
    out[:, 3, 3] = 1.0
    return out


def T_df1_from_of(w) -> np.ndarray:
    """Pose of the reference object's frame {OF} in {DF} at k = 1, alpha = 0.

    This is the rigid part of ``geometry.static_to_detector_frame``:
    ``p_df = R_det^T (R_obj p_of + P - D)``.

    Parameters
    ----------
    w : array_like of shape (13,)
        Static parameters (geometry.STATIC_PARAM_NAMES).

    Returns
    -------
    ndarray of shape (4, 4)
    """
    w = np.asarray(w, dtype=float)
    if w.shape != (13,) or not np.all(np.isfinite(w)):
        raise ValueError(f"static parameters must be 13 finite values, got shape {w.shape}")
    r_det = detector_rotation(w[4], w[5], w[6])
    r_obj = object_rotation(w[10], w[11], w[12])
    return _homogeneous(r_det.T @ r_obj, r_det.T @ (w[7:10] - w[1:4]))


def volume_frame_from_object(geom: DetectorFrameGeometry, motion, T_df1_from_of_) -> np.ndarray:
    """Fixed transform from the object frame {OF} to {VF} of stage position k.

    The object rides on the stage: at alpha = 0 a point moves from its k = 1
    place p_1 to ``R_k + Rot(gamma_k) (p_1 - R_1)`` (geometry.py, eq. 10 note).

    Parameters
    ----------
    geom : geometry.DetectorFrameGeometry
    motion : array_like of shape (6,)
    T_df1_from_of_ : array_like of shape (4, 4)
        Pose of {OF} in {DF} at k = 1, alpha = 0 (e.g. :func:`T_df1_from_of`).

    Returns
    -------
    ndarray of shape (4, 4)
        ``T_vf_from_of``; lengths in metres.
    """
    m = _check_motion(motion)
    t_of = _check_T(T_df1_from_of_, "T_df1_from_of")
    t0 = volume_frame_pose(geom, m)
    g = motion_rotation(m[3], m[4], m[5])
    r1 = np.asarray(geom.stage_df_m, dtype=float)
    t_dfk_from_df1 = _homogeneous(g, r1 + m[:3] - g @ r1)
    t_vf_from_df = _homogeneous(t0[:3, :3].T, -t0[:3, :3].T @ t0[:3, 3])
    return t_vf_from_df @ t_dfk_from_df1 @ t_of


# ----------------------------------------------------------------------------- projection

def _detector_matrix(source_df_m, detector: DetectorSpec) -> np.ndarray:
    """3x4 matrix mapping homogeneous {DF} points to homogeneous (col, row, 1).

    From the central projection onto z_DF = 0 (App. B): with w = z - S_z,
    x w = S_x z - S_z x and y w = S_y z - S_z y; then col = c0 + x / pitch,
    row = r0 - y / pitch.
    """
    sx, sy, sz = source_df_m
    p = detector.pixel_pitch_m
    c0, r0 = detector.centre_px
    return np.array([
        [-sz / p, 0.0, sx / p + c0, -c0 * sz],
        [0.0, sz / p, -sy / p + r0, -r0 * sz],
        [0.0, 0.0, 1.0, -sz],
    ])


def projection_matrices(geom: DetectorFrameGeometry, motion, alpha_rad, detector: DetectorSpec) -> np.ndarray:
    """Per-view 3x4 projection matrices from {VF} [m] to image pixels.

    Parameters
    ----------
    geom : geometry.DetectorFrameGeometry
        The k = 1 geometry in {DF}.
    motion : array_like of shape (6,)
        Error motions of the stage position (zeros for k = 1).
    alpha_rad : array_like of shape (M,)
        Rotary angles of the views [rad].
    detector : geometry.DetectorSpec

    Returns
    -------
    ndarray of shape (M, 3, 4)
        ``[col*w, row*w, w] = P[j] @ [x, y, z, 1]`` for a point (x, y, z) of
        {VF} in metres; (col, row) in the OpenCV pixel convention. Each P is
        scaled so that ``||P[2, :3]|| = 1``: w is then the distance [m] of
        the point from the source measured along the detector normal
        (positive for points in front of the source).
    """
    geom = _check_geom(geom)
    detector = _check_detector(detector)
    t = T_df_from_vf(geom, motion, alpha_rad)
    m_det = _detector_matrix(np.asarray(geom.source_df_m, dtype=float), detector)
    p = np.einsum("ij,mjk->mik", m_det, t)
    return p / np.linalg.norm(p[:, 2, :3], axis=1)[:, None, None]


def project_with_matrices(P, points_m) -> np.ndarray:
    """Apply projection matrices to 3-D points.

    Parameters
    ----------
    P : array_like of shape (M, 3, 4)
    points_m : array_like of shape (N, 3)
        Points in the frame P expects ({VF}) [m].

    Returns
    -------
    ndarray of shape (M, N, 2)
        (col, row) [px].
    """
    p = np.asarray(P, dtype=float)
    if p.ndim != 3 or p.shape[1:] != (3, 4):
        raise ValueError(f"P must have shape (M, 3, 4), got {p.shape}")
    x = np.asarray(points_m, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or not np.all(np.isfinite(x)):
        raise ValueError(f"points_m must be finite with shape (N, 3), got {x.shape}")
    h = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
    q = np.einsum("mij,nj->mni", p, h)
    return q[..., :2] / q[..., 2:3]


def astra_cone_vec(geom: DetectorFrameGeometry, motion, alpha_rad, detector: DetectorSpec,
                   length_unit_m: float = 1e-3) -> np.ndarray:
    """ASTRA ``cone_vec`` rows for the views of one stage position.

    Parameters
    ----------
    geom : geometry.DetectorFrameGeometry
    motion : array_like of shape (6,)
    alpha_rad : array_like of shape (M,)
    detector : geometry.DetectorSpec
    length_unit_m : float, optional
        Length of one ASTRA unit [m]: 1e-3 gives millimetres (default); the
        voxel size gives ASTRA's default unit-voxel volume.

    Returns
    -------
    ndarray of shape (M, 12)
        ``(srcX, srcY, srcZ, dX, dY, dZ, uX, uY, uZ, vX, vY, vZ)`` in ASTRA
        volume coordinates (module docstring: X_a = X_VF, Y_a = -Z_VF,
        Z_a = Y_VF, origin R_k), in units of ``length_unit_m``. ``u`` steps
        one column (+X_DF), ``v`` one row (-Y_DF, down the image).
    """
    geom = _check_geom(geom)
    detector = _check_detector(detector)
    lu = float(length_unit_m)
    if not (np.isfinite(lu) and lu > 0):
        raise ValueError(f"length_unit_m must be a positive finite length, got {length_unit_m}")
    t = T_df_from_vf(geom, motion, alpha_rad)                       # (M, 4, 4)
    rot_vf_from_df = np.transpose(t[:, :3, :3], (0, 2, 1))
    t_vf_from_df = -np.einsum("mij,mj->mi", rot_vf_from_df, t[:, :3, 3])
    a = T_ASTRA_FROM_VF
    pitch = detector.pixel_pitch_m

    def point(p_df):
        return (np.einsum("mij,j->mi", rot_vf_from_df, p_df) + t_vf_from_df) @ a.T / lu

    def vector(v_df):
        return np.einsum("mij,j->mi", rot_vf_from_df, v_df) @ a.T / lu

    src = point(np.asarray(geom.source_df_m, dtype=float))
    d = point(np.zeros(3))
    u = vector(np.array([pitch, 0.0, 0.0]))
    v = vector(np.array([0.0, -pitch, 0.0]))
    return np.concatenate([src, d, u, v], axis=1)


# ----------------------------------------------------------------------------- files

_README = """Calibrated CT geometry for reconstruction (ct_calib_nodes.core.export)

Frames
  {{DF}}  detector frame: origin at the detector centre, +X along image columns,
        +Y opposite to image rows, +Z the detector normal away from the source.
  {{VF}}  reconstruction volume frame of stage position k, fixed to the object:
        origin R_k (stage point on the rotation axis), +Y the rotation axis r_k,
        +Z toward the source at alpha = 0 (perpendicular to r_k), +X = Y x Z. [m]
  {{OF}}  frame of the reference object's CMM certificate (only if given).

Files per stage position k (index kk = 00, 01, ...)
  stage_kk_projection_matrices.npy  (M, 3, 4): [col*w, row*w, w] = P @ [x_vf, y_vf, z_vf, 1],
        x in metres, (col, row) OpenCV pixels (pixel (c, r) centred at (c, r)),
        ||P[2, :3]|| = 1 so w is the depth from the source along the detector normal [m].
  stage_kk_astra_cone_vec.npy / .csv  (M, 12): ASTRA cone_vec rows
        srcX srcY srcZ dX dY dZ uX uY uZ vX vY vZ in units of {unit} m,
        ASTRA axes X_a = X_vf, Y_a = -Z_vf, Z_a = Y_vf; u = next column, v = next row
        (down the image); projection array proj[row, view, col] = image_view[row, col].
  geometry.json: detector, angles [rad], per-stage motions, T_df_from_vf0 (4x4, m),
        T_vf_from_of (4x4, m) when the object pose was given, the file list.

Rotary angles alpha [rad] (view j uses alpha[j]) are in geometry.json and angles_rad.csv.
TIGRE geometry is not exported (see the export module docstring).
"""


def export_geometry_files(out_dir, geom: DetectorFrameGeometry, motions, alpha_rad, detector: DetectorSpec,
                          srd_reported_m=None, T_df1_from_of_=None, length_unit_m: float = 1e-3) -> dict:
    """Write projection matrices and ASTRA cone_vec rows for every stage position.

    Parameters
    ----------
    out_dir : str or Path
        Output directory (created if needed).
    geom : geometry.DetectorFrameGeometry
        The k = 1 geometry in {DF}.
    motions : array_like of shape (K, 6)
        Error motions of each stage position relative to k = 1.
    alpha_rad : array_like of shape (M,)
        Rotary angles of the views [rad], the same at every stage position.
    detector : geometry.DetectorSpec
    srd_reported_m : array_like of shape (K,), optional
        Instrument-reported SRD of each position [m], recorded in the JSON.
    T_df1_from_of_ : array_like of shape (4, 4), optional
        Pose of the reference object's frame at k = 1, alpha = 0 in {DF}; if
        given, T_vf_from_of of every stage position is written too.
    length_unit_m : float, optional
        Unit of the ASTRA rows [m] (default 1e-3, millimetres).

    Returns
    -------
    dict
        ``{"readme": Path, "json": Path, "angles": Path, "stages": [{"k": int,
        "projection_matrices": Path, "astra_npy": Path, "astra_csv": Path}, ...]}``.
    """
    geom = _check_geom(geom)
    detector = _check_detector(detector)
    mot = np.asarray(motions, dtype=float)
    if mot.ndim != 2 or mot.shape[1] != 6 or mot.shape[0] == 0:
        raise ValueError(f"motions must have shape (K, 6) with K >= 1, got {mot.shape}")
    if not np.all(np.isfinite(mot)):
        raise ValueError("motions contain NaN or inf")
    alpha = _check_alpha(alpha_rad)
    srd = None
    if srd_reported_m is not None:
        srd = np.asarray(srd_reported_m, dtype=float)
        if srd.shape != (mot.shape[0],) or not np.all(np.isfinite(srd)):
            raise ValueError(f"srd_reported_m must be {mot.shape[0]} finite values, got shape {srd.shape}")
    t_of = None if T_df1_from_of_ is None else _check_T(T_df1_from_of_, "T_df1_from_of")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)

    readme = out / "README.txt"
    readme.write_text(_README.format(unit=repr(float(length_unit_m))))
    angles = out / "angles_rad.csv"
    np.savetxt(angles, alpha, fmt="%.17g", header="alpha_rad (view index = line index)")

    header = ["srcX", "srcY", "srcZ", "dX", "dY", "dZ", "uX", "uY", "uZ", "vX", "vY", "vZ"]
    stages, stage_meta = [], []
    for k, m in enumerate(mot):
        p = projection_matrices(geom, m, alpha, detector)
        vec = astra_cone_vec(geom, m, alpha, detector, length_unit_m=length_unit_m)
        p_path = out / f"stage_{k:02d}_projection_matrices.npy"
        a_npy = out / f"stage_{k:02d}_astra_cone_vec.npy"
        a_csv = out / f"stage_{k:02d}_astra_cone_vec.csv"
        np.save(p_path, p)
        np.save(a_npy, vec)
        with open(a_csv, "w", newline="") as fh:
            fh.write(f"# ASTRA cone_vec rows of stage position index {k}; unit {float(length_unit_m)!r} m; "
                     "axes X_a=X_vf, Y_a=-Z_vf, Z_a=Y_vf; row j = view j (alpha in angles_rad.csv)\n")
            wr = csv.writer(fh)
            wr.writerow(header)
            for row in vec:
                wr.writerow([f"{x:.17g}" for x in row])
        entry = {"k": k, "projection_matrices": p_path, "astra_npy": a_npy, "astra_csv": a_csv}
        stages.append(entry)
        meta = {
            "k": k,
            "motion": {n: float(x) for n, x in zip(MOTION_PARAM_NAMES, m)},
            "T_df_from_vf0": volume_frame_pose(geom, m).tolist(),
            "projection_matrices": p_path.name,
            "astra_cone_vec": [a_npy.name, a_csv.name],
        }
        if srd is not None:
            meta["srd_reported_m"] = float(srd[k])
        if t_of is not None:
            meta["T_vf_from_of"] = volume_frame_from_object(geom, m, t_of).tolist()
        stage_meta.append(meta)

    doc = {
        "units": {"length": "m", "angle": "rad", "image": "px (OpenCV: pixel (c, r) centred at (c, r))",
                  "astra_length_unit_m": float(length_unit_m)},
        "conventions": {
            "VF": "origin R_k on the rotation axis; +Y rotation axis r_k; +Z toward the source at alpha=0 "
                  "perpendicular to r_k; +X = Y x Z; fixed to the object",
            "projection_matrix": "[col*w,row*w,w] = P @ [x_vf,y_vf,z_vf,1]; ||P[2,:3]|| = 1",
            "astra": "cone_vec rows (src,d,u,v); X_a=X_vf, Y_a=-Z_vf, Z_a=Y_vf; u next column, v next row; "
                     "proj[row, view, col]",
            "motion_order": list(MOTION_PARAM_NAMES),
        },
        "detector": {"cols": int(detector.cols), "rows": int(detector.rows),
                     "pixel_pitch_m": float(detector.pixel_pitch_m)},
        "k1_geometry_df_m": {"source": np.asarray(geom.source_df_m, float).tolist(),
                             "stage": np.asarray(geom.stage_df_m, float).tolist(),
                             "axis": np.asarray(geom.axis_df, float).tolist()},
        "alpha_rad": alpha.tolist(),
        "stages": stage_meta,
    }
    if t_of is not None:
        doc["T_df1_from_of"] = t_of.tolist()
    js = out / "geometry.json"
    js.write_text(json.dumps(doc, indent=1))
    return {"readme": readme, "json": js, "angles": angles, "stages": stages}
