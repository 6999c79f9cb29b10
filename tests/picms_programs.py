"""Part-program YAML text for tests (tests/ is on sys.path through tests/conftest.py)."""

HEADER = """units: SI
part: chrome_targets
lighting: bright_field
placement: {origin_at_stage: [0.0, 0.0, 0.0], tolerance: 0.0005, rotation_about_normal: null}
features:
"""


def chrome_targets_program(*features: str) -> str:
    """The chrome targets at the stage origin (bright field) with ``features``, each one YAML flow
    mapping such as ``{id: c7, type: circle, center: [0.009, -0.008], diameter: 0.007, points: 6}``."""
    return HEADER + "".join(f"  - {f}\n" for f in features)
