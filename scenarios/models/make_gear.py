"""Writes gear.obj, the shipped example of an OBJ mesh scene: a spur gear of
TEETH teeth, extruded THICKNESS_M along +z from z = 0, centred on the z axis,
in metres, as a closed triangle mesh with outward normals (counter-clockwise
faces). Run ``python make_gear.py`` here to write it again."""

from pathlib import Path

import numpy as np

TEETH = 10
TIP_RADIUS_M = 0.020
ROOT_RADIUS_M = 0.016
THICKNESS_M = 0.008


def gear_profile() -> np.ndarray:
    """The gear's outline (n, 2), counter-clockwise seen from +z: each tooth a
    trapezoid, its flanks over the first and last eighth of its pitch (m)."""
    pitch = 2 * np.pi / TEETH
    points = []
    for k in range(TEETH):
        a = k * pitch
        points += [(ROOT_RADIUS_M, a), (TIP_RADIUS_M, a + pitch / 8),
                   (TIP_RADIUS_M, a + 3 * pitch / 8), (ROOT_RADIUS_M, a + pitch / 2)]
    return np.array([(r * np.cos(a), r * np.sin(a)) for r, a in points])


def gear_obj() -> str:
    profile = gear_profile()
    n = len(profile)
    # Vertices (1-based in OBJ): bottom ring 1..n, top ring n+1..2n, then the caps' centres.
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for z in (0.0, THICKNESS_M) for x, y in profile]
    lines += ["v 0 0 0", f"v 0 0 {THICKNESS_M:.6f}"]
    bottom_centre, top_centre = 2 * n + 1, 2 * n + 2
    for i in range(n):
        b0, b1 = i + 1, (i + 1) % n + 1
        t0, t1 = b0 + n, b1 + n
        lines += [f"f {b0} {b1} {t1}", f"f {b0} {t1} {t0}",  # the side, facing out
                  f"f {top_centre} {t0} {t1}", f"f {bottom_centre} {b1} {b0}"]  # the caps
    return "# A spur gear, metres (scenarios/models/make_gear.py)\n" + "\n".join(lines) + "\n"


if __name__ == "__main__":
    Path(__file__).with_name("gear.obj").write_text(gear_obj())
