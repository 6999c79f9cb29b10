"""metro_msgs/SphereObservationArray for CT node tests: what the detector would publish for one frame."""


def observation_array(stamp_ns: int, alpha, srd, ids, uv, sigma_px: float = 0.05):
    """One frame's observations: sphere ``ids`` at centres ``uv`` (col, row) [px] of a 1024^2 detector,
    stamped ``stamp_ns``, at rotary angle ``alpha`` [rad] and reported SRD ``srd`` [m]."""
    from builtin_interfaces.msg import Time  # noqa: PLC0415
    from metro_msgs.msg import SphereObservation, SphereObservationArray  # noqa: PLC0415

    a = SphereObservationArray(rotary_angle_rad=float(alpha), srd_reported_m=float(srd), image_cols=1024,
                               image_rows=1024)
    a.header.stamp = Time(sec=int(stamp_ns // 1_000_000_000), nanosec=int(stamp_ns % 1_000_000_000))
    a.observations = [SphereObservation(sphere_id=int(i), col_px=float(c), row_px=float(r), sigma_px=float(sigma_px))
                      for i, (c, r) in zip(ids, uv)]
    return a
