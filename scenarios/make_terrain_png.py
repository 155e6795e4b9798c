"""Writes terrain.png, the terrain scenario's heightmap (deformable_surface.yaml,
``terrain``): 64 x 64 pixels, 16-bit greyscale, the same bytes every run.

    python -m maglev_haptics.scenarios.make_terrain_png

Seen from above (image row 0 at the lattice's far edge, +y; column 0 at -x): a
round hill in the far-left quarter, a crater (a ring wall round a floor at black)
in the near-right one, on a black plain. Positions are fractions of the image's
width and height, so they follow the lattice's size_m.
"""

from pathlib import Path

import numpy as np
from PIL import Image

SIZE_PX = 64
TERRAIN_PNG = Path(__file__).resolve().parent / "terrain.png"


def terrain_greys() -> np.ndarray:
    """(rows, columns) greys in [0, 1]: the hill's top is white, the crater's wall 0.6."""
    # Pixel centres as fractions of the image: u along a row (x), v down a column (-y).
    v, u = np.mgrid[0:SIZE_PX, 0:SIZE_PX] / (SIZE_PX - 1)
    hill = np.exp(-((u - 1 / 3) ** 2 + (v - 1 / 3) ** 2) / (2 * 0.11 ** 2))
    ring_radius = np.hypot(u - 0.69, v - 0.67)
    crater = 0.6 * np.exp(-(ring_radius - 0.11) ** 2 / (2 * 0.035 ** 2))
    return np.maximum(hill, crater)


def write_terrain_png(path: Path = TERRAIN_PNG) -> None:
    grey16 = np.round(65535 * terrain_greys()).astype(np.uint16)
    Image.fromarray(grey16).save(path, optimize=True)


if __name__ == "__main__":
    write_terrain_png()
    print(f"wrote {TERRAIN_PNG}")
