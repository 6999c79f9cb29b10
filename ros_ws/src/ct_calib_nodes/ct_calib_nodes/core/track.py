"""Windowed sphere detection for frame sequences (issue 14, item 4): the full detector on a crop.

Within one stage position consecutive projections differ by a small rotation, so the shadows of
a frame lie close to where the previous frame had them. ``TrackingDetector`` runs the full
detector (``detect.detect_spheres``, unchanged) on the whole frame at a *key frame*, and on later
frames only on the rectangle that holds the previous frame's shadows (accepted and refused) plus
a margin: the flat field, the segmentation background and the candidate search, which cost
about half of a 1024^2 detection and scale with the pixel count, then see about half the pixels.
The centres are moved back to frame pixels.

A windowed result is used only when it cannot have missed anything the full frame holds near the
object; otherwise the frame is detected again on the whole frame (a *fallback*):

- a shadow (accepted or refused) lies within ``guard`` pixels of a crop edge that is not an image
  edge (the object may reach beyond the crop, or the segmentation background near the crop edge
  may differ from the full frame's);
- fewer shadows were accepted than in the previous frame minus ``max_drop``;
- the crop's detection raised (bad frame: the full detection then raises with the full-frame
  message) or the frame does not have the expected shape.

The margin is ``margin_diameters`` x the largest expected shadow diameter plus the segmentation
background's closing length, so a shadow moved by up to about one diameter between frames is
still measured with the same background as on the whole frame. What the crop can change: the
crop's noise estimate and the background near its edges; the windowed centres agree with the full
detector's well inside their standard deviation (tests/ct_core/test_track.py).

Results depend only on the frames of one block (key frame + the frames after it, up to the next
key frame) in order, never on which process runs the block: sequential and parallel replay give
the same results bit for bit when they use the same blocks.

The numerical core: no ROS imports.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .detect import FrameError, detect_spheres


@dataclass(frozen=True)
class TrackSettings:
    """Windowed detection: when to detect the whole frame, how large the crop is."""

    block_frames: int = 12          # a key frame (full detection) at least every this many frames
    margin_diameters: float = 0.5   # motion allowance beyond the guard band, in largest shadow diameters
    max_drop: int = 2               # fewer accepted than the previous frame minus this: full detection

    def __post_init__(self):
        if int(self.block_frames) < 1:
            raise ValueError(f"block_frames must be >= 1, got {self.block_frames}")
        if not (np.isfinite(self.margin_diameters) and self.margin_diameters >= 0):
            raise ValueError(f"margin_diameters must be finite and >= 0, got {self.margin_diameters}")
        if int(self.max_drop) < 0:
            raise ValueError(f"max_drop must be >= 0, got {self.max_drop}")


def _crop_of(arr, r0, r1, c0, c1):
    """A flat-field / dark argument cropped like the frame (scalars and None pass unchanged)."""
    if arr is None or np.ndim(arr) == 0:
        return arr
    return np.asarray(arr)[r0:r1, c0:c1]


def _shift(det, dx: float, dy: float):
    """FrameDetections of a crop moved to frame pixels (``centre_corrected_px`` is not made here)."""
    off = np.array([dx, dy], dtype=np.float64)
    rej = det.rejected
    rej = dataclasses.replace(rej, centre_px=np.asarray(rej.centre_px, dtype=np.float64).reshape(-1, 2) + off)
    hot = det.hot_pixels_px
    if hot is not None:
        hot = np.asarray(hot, dtype=np.float64).reshape(-1, 2) + off
    return dataclasses.replace(det, centre_px=np.asarray(det.centre_px, dtype=np.float64).reshape(-1, 2) + off,
                               rejected=rej, hot_pixels_px=hot)


class TrackingDetector:
    """Full detection at key frames, windowed detection (full detector on a crop) in between.

    ``detect(image, encoding, srd_m, key)``: ``key`` True starts a block (full detection, the
    state forgotten). ``counts`` tallies 'full', 'window' and 'fallback' frames.
    """

    def __init__(self, flat_field_counts=None, dark=None, expected_shape=None, settings: TrackSettings | None = None,
                 detection_settings=None):
        self.flat = flat_field_counts
        self.dark = dark
        self.shape = tuple(expected_shape) if expected_shape is not None else None
        self.settings = settings if settings is not None else TrackSettings()
        self.detection_settings = detection_settings
        self._prev = None           # (FrameDetections, srd) of the previous frame of this block
        self.counts = {"full": 0, "window": 0, "fallback": 0}

    def reset(self):
        self._prev = None

    def _full(self, image, encoding, drange, timing):
        return detect_spheres(image, encoding=encoding, flat_field_counts=self.flat, dark=self.dark,
                              expected_shape=self.shape, diameter_px_range=drange,
                              settings=self.detection_settings, timing=timing)

    def crop_box(self, prev, shape, drange):
        """(r0, r1, c0, c1, guard) of the crop round the previous frame's shadows, or None."""
        pts = np.vstack([np.asarray(prev.centre_px, dtype=np.float64).reshape(-1, 2),
                         np.asarray(prev.rejected.centre_px, dtype=np.float64).reshape(-1, 2)])
        if len(pts) == 0:
            return None
        st = self.detection_settings
        tol = st.size_tolerance if st is not None else 0.25
        closing = 1.5 * float(drange[1]) * (1.0 + tol) + 7.0   # the segmentation background's line length
        if st is not None and st.background_window_px is not None:
            closing = float(st.background_window_px)
        axes = np.asarray(prev.semi_axes_px, dtype=np.float64).reshape(-1, 2)
        d_seen = 2.0 * float(axes.max()) if len(axes) else float(drange[1])   # largest shadow of the frame
        guard = 0.5 * closing + 0.5 * d_seen + 2.0          # a shadow this close to a crop edge: full frame
        margin = guard + self.settings.margin_diameters * d_seen
        rows, cols = shape
        lo = np.floor(pts.min(axis=0) - margin).astype(int)
        hi = np.ceil(pts.max(axis=0) + margin).astype(int) + 1
        c0, r0 = max(0, lo[0]), max(0, lo[1])
        c1, r1 = min(cols, hi[0]), min(rows, hi[1])
        # even offsets and sizes: the segmentation background's half-resolution grid stays aligned
        c0, r0 = c0 - c0 % 2, r0 - r0 % 2
        c1, r1 = c1 - (c1 - c0) % 2, r1 - (r1 - r0) % 2
        if (r1 - r0) * (c1 - c0) > 0.85 * rows * cols:
            return None                                      # hardly smaller: the whole frame
        return r0, r1, c0, c1, guard

    def _windowed_ok(self, det, box, shape, prev):
        r0, r1, c0, c1, guard = box
        rows, cols = shape
        pts = np.vstack([np.asarray(det.centre_px).reshape(-1, 2), np.asarray(det.rejected.centre_px).reshape(-1, 2)])
        if len(pts):
            x, y = pts[:, 0], pts[:, 1]
            near = ((c0 > 0) & (x < c0 + guard)) | ((c1 < cols) & (x > c1 - 1 - guard)) | \
                   ((r0 > 0) & (y < r0 + guard)) | ((r1 < rows) & (y > r1 - 1 - guard))
            if np.any(near):
                return False
        return len(det.centre_px) >= len(prev.centre_px) - int(self.settings.max_drop)

    def detect(self, image, encoding: str, drange, key: bool = False, srd_m: float | None = None,
               timing: dict | None = None):
        """Detections of one frame; raises detect.FrameError exactly when the full detector does."""
        if key or self._prev is None or (srd_m is not None and self._prev[1] != srd_m):
            self._prev = None
        image = np.asarray(image)
        box = None
        if self._prev is not None and drange is not None and (self.shape is None or image.shape == self.shape):
            box = self.crop_box(self._prev[0], image.shape[:2], drange)
        if box is None:
            self._prev = None
            det = self._full(image, encoding, drange, timing)
            self.counts["full"] += 1
        else:
            r0, r1, c0, c1, _g = box
            try:
                det = detect_spheres(image[r0:r1, c0:c1], encoding=encoding,
                                     flat_field_counts=_crop_of(self.flat, r0, r1, c0, c1),
                                     dark=_crop_of(self.dark, r0, r1, c0, c1), diameter_px_range=drange,
                                     settings=self.detection_settings, timing=timing)
                det = _shift(det, c0, r0)
                ok = self._windowed_ok(det, box, image.shape[:2], self._prev[0])
            except FrameError:
                ok = False
            if ok:
                self.counts["window"] += 1
            else:
                self._prev = None
                det = self._full(image, encoding, drange, timing)
                self.counts["fallback"] += 1
        self._prev = (det, srd_m)
        return det
