"""Heightmaps for the deformable landscape: pseudo-random, a sum of two sine waves,
or a greyscale image.

A heightmap gives the height (m) of the landscape's surface above its mean level
at each point of a rectangular grid of columns, x_m (nx,) by y_m (ny,) in W (m),
both uniformly spaced and ascending. It fixes the surface the user sees; the
lattice beneath it is built by ``lattice_construction.build_lattice``.

- ``RandomHeightmap``: Gaussian-correlated noise. Its correlation length L is the
  lag at which the height's autocorrelation falls to 1/e: the ideal field's
  normalized autocorrelation is exp(-r^2 / L^2) at horizontal distance r (the
  usual Gaussian rough-surface model). It is made by smoothing white noise with
  a Gaussian kernel of standard deviation L / 2 (in m; L / (2 dx) grid cells
  along x, L / (2 dy) along y), since a Gaussian of standard deviation s
  convolved with itself is a Gaussian of standard deviation s sqrt(2). The grid
  samples this faithfully for L >= ~1.6 spacings (the autocorrelation at one
  spacing is within 0.005 of the ideal); for shorter L the sampled kernel
  under-correlates neighbours (0.26 instead of 0.37 at L = one spacing), and
  below half a spacing, where the ideal correlation between neighbours is under
  exp(-4) = 0.02, the heights are, correctly, nearly independent.
- ``SineHeightmap``: a_x sin(2 pi x / l_x + phi_x) + a_y sin(2 pi y / l_y + phi_y).
- ``ImageHeightmap``: an 8- or 16-bit greyscale image (a PNG, or any greyscale
  file Pillow reads) stretched over the grid and seen from above: its column 0 at
  the lowest x, its row 0 (the picture's top) at the highest y, its corner pixels'
  centres on the grid's corner columns, so the picture looks in Meshcat's top view
  as in an image viewer. Black is lowest and white ``height_m`` above it, in
  proportion to grey over the bit depth's maximum (255 or 65535), so the same
  picture at either depth gives the same heights; like a random map it is
  de-meaned over the grid. Each column takes the image's bilinear interpolation
  at its position: a picture finer than the columns is sampled, not averaged
  (blur it first if that aliases). Colour images are refused, not guessed at:
  convert them to greyscale first.
"""

import math
import typing
from dataclasses import dataclass, field
from typing import List, Union

import numpy as np
from PIL import Image, UnidentifiedImageError
from scipy.ndimage import gaussian_filter, map_coordinates

from maglev_haptics.hardware.config_checks import finite, require

# Relative deviation of a grid's spacings from their mean still called uniform:
# np.linspace's spacings differ by a few ulps.
UNIFORM_SPACING_RTOL = 1e-6


@dataclass
class RandomHeightmap:
    """Gaussian-correlated pseudo-random heights, zero mean, exactly the given RMS.

    The heights depend on the seed and on the grid (its shape and spacing): the
    same seed on the same grid gives the same map."""

    seed: int = 0  # seeds np.random.default_rng; an integer >= 0
    amplitude_m: float = 0.0008  # RMS height over the grid (m)
    # Lag at which the autocorrelation falls to 1/e (m); the smoothing kernel's
    # standard deviation is half of it (see the module docstring).
    correlation_length_m: float = 0.004

    def validate(self, path: str = "heightmap") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        require(isinstance(self.seed, (int, np.integer)) and not isinstance(self.seed, bool)
                and self.seed >= 0, f"{path}.seed", self.seed, "must be an integer >= 0")
        require(finite(self.amplitude_m) and self.amplitude_m >= 0, f"{path}.amplitude_m",
                self.amplitude_m, "must be a finite RMS height >= 0 (m)")
        require(finite(self.correlation_length_m) and self.correlation_length_m > 0,
                f"{path}.correlation_length_m", self.correlation_length_m,
                "must be a finite length > 0 (m)")


@dataclass
class SineHeightmap:
    """a_x sin(2 pi x / l_x + phi_x) + a_y sin(2 pi y / l_y + phi_y), x and y in W (m)."""

    amplitude_m: List[float] = field(default_factory=lambda: [0.001, 0.0005])  # a_x, a_y (m)
    wavelength_m: List[float] = field(default_factory=lambda: [0.02, 0.015])  # l_x, l_y (m)
    phase_rad: List[float] = field(default_factory=lambda: [0.0, 0.0])  # phi_x, phi_y (rad)

    def validate(self, path: str = "heightmap") -> None:
        """Range checks; a ValueError names ``path.field``, its value and what is allowed."""
        _pair(f"{path}.amplitude_m", self.amplitude_m, 0.0, False, "x and y amplitudes, m")
        _pair(f"{path}.wavelength_m", self.wavelength_m, 0.0, True, "x and y wavelengths, m")
        _pair(f"{path}.phase_rad", self.phase_rad, -math.inf, False, "x and y phases, rad")


@dataclass
class ImageHeightmap:
    """Heights from a greyscale image seen from above (see the module docstring):
    black lowest, white ``height_m`` above it.

    ``file`` is the image's path: in a scenario file relative to that file's folder
    (in ``--scenario-text``, to the working directory); in Python, to the working
    directory."""

    file: str = ""  # an 8-bit (L) or 16-bit (I;16) greyscale image; required
    height_m: float = 0.004  # white's height above black (m)

    def validate(self, path: str = "heightmap") -> None:
        """Range checks and a read of the image; a ValueError names ``path.field``, its
        value and what is allowed."""
        require(finite(self.height_m) and self.height_m > 0, f"{path}.height_m",
                self.height_m, "must be a finite height > 0 (m), white's above black")
        read_grey_image(self.file, f"{path}.file")


Heightmap = Union[RandomHeightmap, SineHeightmap, ImageHeightmap]

# Pillow's greyscale modes read here, and the largest grey of each: 16-bit PNGs open
# as I;16 in current Pillow, as 32-bit I (still 16-bit values) in older releases.
GREY_MODE_MAX = {"L": 255, "I;16": 65535, "I;16B": 65535, "I;16L": 65535, "I": 65535}


def heightmap_heights(config: Heightmap, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
    """(nx, ny) heights (m) of the surface above its mean level at the grid points
    (x_m[ix], y_m[iy]) in W (m); x_m (nx,) and y_m (ny,) uniformly spaced and
    ascending. A random or an image map is de-meaned over the grid; a sine map's
    mean level is its waves' mean over whole periods. Raises ValueError for an
    invalid config (an image map's unreadable image among them) or grid."""
    require(isinstance(config, typing.get_args(Heightmap)), "heightmap", config,
            "must be a RandomHeightmap, a SineHeightmap or an ImageHeightmap")
    config.validate(type(config).__name__)
    # A random map's smoothing needs a spacing per axis, an image an extent to span:
    # at least 2 points.
    min_points = 1 if isinstance(config, SineHeightmap) else 2
    x_m = validate_grid_axis("x_m", x_m, min_points)
    y_m = validate_grid_axis("y_m", y_m, min_points)
    if isinstance(config, SineHeightmap):
        (a_x, a_y), (l_x, l_y), (phi_x, phi_y) = (config.amplitude_m, config.wavelength_m,
                                                  config.phase_rad)
        return (a_x * np.sin(2 * np.pi * x_m / l_x + phi_x))[:, None] \
            + (a_y * np.sin(2 * np.pi * y_m / l_y + phi_y))[None, :]
    if isinstance(config, ImageHeightmap):
        return image_heights(read_grey_image(config.file, "ImageHeightmap.file"),
                             config.height_m, x_m, y_m)
    return _random_heights(config, x_m[1] - x_m[0], y_m[1] - y_m[0], (len(x_m), len(y_m)))


def _random_heights(config: RandomHeightmap, dx_m: float, dy_m: float, shape) -> np.ndarray:
    noise = np.random.default_rng(config.seed).standard_normal(shape)
    kernel_sigma_m = config.correlation_length_m / 2
    # mode="wrap" keeps the noise statistically the same everywhere: "reflect" would
    # count the noise near an edge twice, raising the variance and the correlation
    # there. The price is that opposite edges of the map match, which the lattice's
    # fixed edge columns hide.
    smooth = gaussian_filter(noise, sigma=(kernel_sigma_m / dx_m, kernel_sigma_m / dy_m),
                             mode="wrap")
    smooth -= smooth.mean()
    rms = math.sqrt(np.mean(smooth ** 2))
    # A zero map (all noise smoothed away) stays zero rather than dividing by 0.
    return smooth * (config.amplitude_m / rms) if rms > 0 else smooth


def image_heights(grey: np.ndarray, height_m: float, x_m: np.ndarray,
                  y_m: np.ndarray) -> np.ndarray:
    """(nx, ny) heights (m) about their mean from the (rows, columns) greys in [0, 1]
    stretched over the grid x_m (nx,) by y_m (ny,) (m, ascending, >= 2 points each):
    image column 0 at x_m[0], row 0 at y_m[-1], bilinear between pixel centres; grey
    g stands g * height_m above black."""
    rows, columns = grey.shape
    image_column = (x_m - x_m[0]) / (x_m[-1] - x_m[0]) * (columns - 1)
    image_row = (y_m[-1] - y_m) / (y_m[-1] - y_m[0]) * (rows - 1)
    at_rows, at_columns = np.broadcast_arrays(image_row[None, :], image_column[:, None])
    # mode="nearest" only absorbs rounding past the edge pixels' centres.
    heights = height_m * map_coordinates(grey, [at_rows, at_columns], order=1, mode="nearest")
    return heights - heights.mean()


def read_grey_image(file: str, path: str) -> np.ndarray:
    """The greyscale image at ``file`` as (rows, columns) float64 greys in [0, 1], each
    pixel's value over its bit depth's maximum (GREY_MODE_MAX). A ValueError names
    ``path``, the file and what is wrong: no such file, not an image, not greyscale
    (colour is refused), smaller than 2 x 2 pixels, or 32-bit values past 16 bits."""
    require(isinstance(file, str) and file != "", path, file,
            "must name an 8- or 16-bit greyscale image file")
    try:
        with Image.open(file) as image:
            mode, (columns, rows) = image.mode, image.size
            require(mode in GREY_MODE_MAX, path, file,
                    f"has Pillow mode {mode}: must be 8- or 16-bit greyscale (mode L or "
                    "I;16); convert it to greyscale first")
            require(rows >= 2 and columns >= 2, path, file,
                    f"is {columns} x {rows} pixels: must be at least 2 x 2")
            values = np.asarray(image)
    except FileNotFoundError:
        raise ValueError(f"{path} = {file!r}: no such file; must be an 8- or 16-bit "
                         "greyscale image") from None
    except UnidentifiedImageError:
        raise ValueError(f"{path} = {file!r}: not an image Pillow can read; must be an 8- "
                         "or 16-bit greyscale image (PNG)") from None
    except OSError as error:  # a folder, no permission, a truncated image
        raise ValueError(f"{path} = {file!r}: cannot be read ({error.strerror or error}); "
                         "must be an 8- or 16-bit greyscale image") from None
    largest = GREY_MODE_MAX[mode]
    require(values.min() >= 0 and values.max() <= largest, path, file,
            f"holds values from {values.min()} to {values.max()}: must be 0..{largest}")
    return values.astype(float) / largest


def validate_grid_axis(name: str, values, min_points: int) -> np.ndarray:
    """``values`` as a float64 (n,) array after checking it is 1-D, has at least
    ``min_points`` finite values, ascending and uniformly spaced (spacings within
    UNIFORM_SPACING_RTOL of their mean); else ValueError naming ``name``."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 1 or len(values) < min_points:
        raise ValueError(f"{name} has shape {values.shape}: must be a 1-D array of at "
                         f"least {min_points} grid coordinates (m)")
    bad = np.flatnonzero(~np.isfinite(values))
    if len(bad):
        raise ValueError(f"{name}[{bad[0]}] = {float(values[bad[0]])!r}: must be finite")
    if len(values) > 1:
        spacing = np.diff(values)
        if np.any(spacing <= 0):
            i = int(np.flatnonzero(spacing <= 0)[0])
            raise ValueError(f"{name}[{i + 1}] = {float(values[i + 1])!r} after {name}[{i}] = "
                             f"{float(values[i])!r}: must be strictly ascending")
        mean = spacing.mean()
        if np.max(np.abs(spacing - mean)) > UNIFORM_SPACING_RTOL * mean:
            raise ValueError(f"{name} spacing ranges from {float(spacing.min())!r} to "
                             f"{float(spacing.max())!r} m: must be uniform (within "
                             f"{UNIFORM_SPACING_RTOL:g} of the mean)")
    return values


# --- validation -----------------------------------------------------------------------

def _pair(path: str, values, minimum: float, strict: bool, meaning: str) -> None:
    ok = (isinstance(values, (list, tuple)) and len(values) == 2
          and all(finite(v) and (v > minimum if strict else v >= minimum) for v in values))
    bound = "" if minimum == -math.inf else f" {'>' if strict else '>='} {minimum:g}"
    require(ok, path, values, f"must be a list of 2 finite numbers{bound} ({meaning})")
