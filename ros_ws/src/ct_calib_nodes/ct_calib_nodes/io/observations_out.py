"""FrameResult (core) -> metro_msgs/SphereObservationArray."""

import math


def observation_array_msg(fr, stamp, detector):
    from metro_msgs.msg import SphereObservation, SphereObservationArray  # noqa: PLC0415

    m = SphereObservationArray()
    m.header.stamp = stamp
    m.header.frame_id = "ct_detector"
    m.rotary_angle_rad = float(fr.alpha_rad)
    m.srd_reported_m = float(fr.srd_reported_m)
    m.image_cols, m.image_rows = int(detector.cols), int(detector.rows)
    f = lambda v: float(v) if math.isfinite(float(v)) else float("nan")  # noqa: E731
    for i in range(len(fr.ids)):
        m.observations.append(SphereObservation(
            sphere_id=int(fr.ids[i]), flag=int(fr.flag[i]), reason=str(fr.reason[i]),
            col_px=f(fr.centre_px[i, 0]), row_px=f(fr.centre_px[i, 1]), sigma_px=f(fr.sigma_px[i]),
            semi_major_px=f(fr.semi_axes_px[i, 0]), semi_minor_px=f(fr.semi_axes_px[i, 1]),
            angle_rad=f(fr.angle_rad[i]), fit_rms_px=f(fr.fit_rms_px[i]),
            systematic_col_px=0.0 if fr.systematic_px is None else f(fr.systematic_px[i, 0]),
            systematic_row_px=0.0 if fr.systematic_px is None else f(fr.systematic_px[i, 1])))
    return m
