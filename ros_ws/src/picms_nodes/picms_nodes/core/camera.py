"""Pinhole camera with plumb_bob distortion, rotations, and the sphere silhouette cone.

Frames: the stage frame `stage` (INTERFACES.md, PiCMS) and the ROS optical frame of each
camera (+Z forward, +X right, +Y down). A camera pose is `R_stage_camera` (columns: the
camera axes in the stage frame) and `p_stage_centre` (perspective centre in the stage frame).
Pixel (col c, row r) has its centre at (c, r) (OpenCV convention).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


def rotvec_to_matrix(rv) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle, rad), shape (3,) -> (3, 3)."""
    rv = np.asarray(rv, dtype=np.float64).reshape(3)
    th = float(np.linalg.norm(rv))
    k = np.array([[0, -rv[2], rv[1]], [rv[2], 0, -rv[0]], [-rv[1], rv[0], 0]])
    if th < 1e-12:
        return np.eye(3) + k
    k = k / th
    return np.eye(3) + np.sin(th) * k + (1 - np.cos(th)) * (k @ k)


def matrix_to_rotvec(R) -> np.ndarray:
    """Rotation vector of a rotation matrix, shape (3, 3) -> (3,)."""
    rv, _ = cv2.Rodrigues(np.asarray(R, dtype=np.float64))
    return rv.reshape(3)


def rotation_angle_rad(R_a, R_b) -> float:
    """Angle of R_a^T R_b (rad): the rotation error between two orientations."""
    c = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def check_points(points, name="points", cols=3) -> np.ndarray:
    """Float64 array of shape (N, cols), finite; raise ValueError naming what is wrong."""
    a = np.asarray(points, dtype=np.float64)
    if a.ndim == 1 and a.size == cols:
        a = a.reshape(1, cols)
    if a.ndim != 2 or a.shape[1] != cols:
        raise ValueError(f"{name}: expected an array of shape (N, {cols}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or inf")
    return a


@dataclass(frozen=True)
class Intrinsics:
    """What a CameraInfo carries: K (3, 3), D (5,) plumb_bob [k1, k2, p1, p2, k3], size."""
    K: np.ndarray
    D: np.ndarray
    width: int
    height: int

    def __post_init__(self):
        K = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        D = np.zeros(5)
        d = np.asarray(self.D, dtype=np.float64).ravel()
        if d.size > 5 or not np.all(np.isfinite(d)) or not np.all(np.isfinite(K)):
            raise ValueError("intrinsics: K must be 3x3 finite, D at most 5 finite plumb_bob terms")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0:
            raise ValueError(f"intrinsics: K is not a camera matrix (fx, fy > 0, K[2,2] = 1): {K.tolist()}")
        D[:d.size] = d
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)

    @property
    def f_px(self) -> float:
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    def distort(self, xn) -> np.ndarray:
        """Pixels (N, 2) of normalised, undistorted image coordinates xn (N, 2)."""
        xn = check_points(xn, "xn", 2)
        k1, k2, p1, p2, k3 = self.D
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        K = self.K
        return np.column_stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]])

    def undistort(self, px) -> np.ndarray:
        """Normalised, undistorted coordinates (N, 2) of pixels px (N, 2) (iterative inverse)."""
        px = check_points(px, "px", 2)
        if not np.any(self.D):
            K = self.K
            y = (px[:, 1] - K[1, 2]) / K[1, 1]
            x = (px[:, 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
            return np.column_stack([x, y])
        K = self.K
        yd = (px[:, 1] - K[1, 2]) / K[1, 1]
        xd = (px[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
        x, y = undistort_normalised(self.D, xd, yd)
        return np.column_stack([x, y])


def undistort_normalised(D, xd, yd, iterations: int = 20):
    """Invert plumb_bob distortion D (5,) on normalised distorted coordinates (fixed point)."""
    k1, k2, p1, p2, k3 = D
    x, y = np.array(xd, dtype=np.float64), np.array(yd, dtype=np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        xn = (xd - dx) / rad
        yn = (yd - dy) / rad
        step = max(float(np.max(np.abs(xn - x), initial=0.0)), float(np.max(np.abs(yn - y), initial=0.0)))
        x, y = xn, yn
        if step < 1e-15:        # converged (normalised units: ~1e-11 px)
            break
    return x, y


@dataclass(frozen=True)
class CameraPose:
    """R_stage_camera (3, 3) and p_stage_centre (3,) in m."""
    R_stage_camera: np.ndarray
    p_stage_centre: np.ndarray

    def to_camera(self, points_stage) -> np.ndarray:
        """Points (N, 3) in the stage frame -> camera optical frame (N, 3)."""
        p = check_points(points_stage, "points_stage")
        return (p - self.p_stage_centre) @ self.R_stage_camera

    def normalised(self, points_stage) -> np.ndarray:
        """Normalised image coordinates (N, 2) of stage-frame points (N, 3)."""
        pc = self.to_camera(points_stage)
        if np.any(pc[:, 2] <= 0):
            raise ValueError("point behind the camera")
        return pc[:, :2] / pc[:, 2:3]


def project(pose: CameraPose, intr: Intrinsics, points_stage) -> np.ndarray:
    """Pixel coordinates (N, 2) of stage-frame points (N, 3) through pose and intrinsics."""
    return intr.distort(pose.normalised(points_stage))


def silhouette_axis_px(pose: CameraPose, intr: Intrinsics, centre_stage) -> np.ndarray:
    """Image of a sphere centre (1, 2): the point the silhouette cone's axis pierces.

    This is what `detect.detect_disc` returns as `centre_px`: the projected sphere centre,
    not the centre of the silhouette ellipse (they differ off axis under true perspective).
    """
    return project(pose, intr, centre_stage)
