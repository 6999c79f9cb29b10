"""Resident-size sampling shared by the soak and memory benchmarks (imported as a sibling module:
the scripts run as `python tests/benchmarks/<name>.py`, which puts this folder on sys.path)."""
import numpy as np


def rss_mib(pid) -> float:
    """VmRSS of a process in MiB from /proc; NaN once it has gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        pass
    return float("nan")


def rss_summary(samples):
    """start/end/peak RSS and the growth slope over the second half of [(t_s, rss_mib), ...]; None if empty."""
    arr = np.array(samples, float)
    if arr.size == 0:
        return None
    half = arr[arr[:, 0] >= arr[-1, 0] / 2]
    slope = float(np.polyfit(half[:, 0] / 60.0, half[:, 1], 1)[0]) if len(half) >= 3 else float("nan")
    return {"start_mib": round(float(arr[0, 1]), 1), "end_mib": round(float(arr[-1, 1]), 1),
            "peak_mib": round(float(np.nanmax(arr[:, 1])), 1),
            "growth_second_half_mib_per_min": round(slope, 2) if np.isfinite(slope) else None}
