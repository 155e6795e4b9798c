"""The deformable landscape's mass-spring lattice, built from a heightmap.

The paper's three phases (section V, Figs. 7 and 8), made exact:

1. Heights. ``surface_z_m[ix, iy]`` is the absolute height h in W (m) of the
   surface vertex of column (ix, iy), which stands at (x_m[ix], y_m[iy]).
2. Masses. A vertical grid of levels z_k = base_z_m + k * level_spacing_m,
   k = 0, 1, ..., is laid under the surface; the levels strictly below h become
   masses (count_below = ceil((h - base) / dz) of them, a level within
   LEVEL_TOLERANCE of h counting as on it, so not below), and the surface vertex
   is put on top. The masses are then respaced uniformly (Fig. 7c), which avoids
   the short links a level just under the surface would make (Fig. 7b): mass j of
   the column sits at z = base + j (h - base) / count_below, j = 0..count_below,
   the last being the surface vertex at h. So the bottom mass of every column is
   at base_z_m, and horizontally adjacent masses need not be at the same height.
3. Links. (1) Each mass (ix, iy, j) is linked to each of its up to 26 neighbours
   (ix + a, iy + b, j + c), a, b, c in {-1, 0, 1} not all zero, that exists
   (0 <= j + c < that column's count), against inversions of the lattice.
   (2) Each surface vertex is linked to the surface vertices of its up to 8
   horizontally adjacent columns. (3) For adjacent columns A and B (8-neighbourhood)
   with h_A > h_B, each mass of A below A's surface vertex and strictly above h_B
   is linked to B's surface vertex (Fig. 8), so a tall column's side is held by
   its lower neighbours' surfaces. A pair linked by several rules gets one link.
   Rest lengths are the lengths at construction.

Masses are numbered column by column, x-major (ix outer, iy inner), bottom to top
within a column. The bottom level and the edge columns are fixed (the paper's
infinite masses).
"""

from dataclasses import dataclass

import numpy as np

from maglev_haptics.systems.heightmap import validate_grid_axis

# A surface within this fraction of a level spacing above a level counts as on the
# level, which is then not below the surface: h = base + 6 dz with base = -0.030,
# dz = 0.003 gives (h - base) / dz = 6.000000000000001, which must mean 6 levels
# below, not 7.
LEVEL_TOLERANCE = 1e-9
# Above this many masses the link arrays alone take gigabytes; a haptic-rate
# lattice has at most ~1e5.
MAX_MASSES = 1_000_000
# Horizontal column offsets (a, b) covering each unordered pair of 8-adjacent
# columns once: the other four are their negatives.
HALF_NEIGHBOURHOOD = ((1, -1), (1, 0), (1, 1), (0, 1))


@dataclass
class Lattice:
    """A built lattice; lengths in m, positions in W, indices into the masses."""

    x_m: np.ndarray  # (nx,) column x positions in W (m)
    y_m: np.ndarray  # (ny,) column y positions in W (m)
    positions_m: np.ndarray  # (n, 3) float64 rest positions of the masses in W (m)
    fixed: np.ndarray  # (n,) bool: bottom-level and edge-column masses
    links: np.ndarray  # (m, 2) int64 mass pairs, each row i < j, unique, sorted lexicographically
    rest_lengths_m: np.ndarray  # (m,) float64 rest lengths (m), > 0
    column_start: np.ndarray  # (nx, ny) int64 index of each column's bottom mass
    # (nx, ny) int64 masses in each column (>= 2), contiguous from bottom to top
    column_count: np.ndarray
    surface: np.ndarray  # (nx, ny) int64 index of each column's surface vertex
    # (2 (nx-1) (ny-1), 3) int64 surface vertices, counter-clockwise seen from +z
    surface_triangles: np.ndarray

    @property
    def num_masses(self) -> int:
        return len(self.positions_m)

    @property
    def num_links(self) -> int:
        return len(self.links)

    @property
    def num_free(self) -> int:
        return int(np.count_nonzero(~self.fixed))


def build_lattice(surface_z_m: np.ndarray, x_m: np.ndarray, y_m: np.ndarray,
                  base_z_m: float, level_spacing_m: float) -> Lattice:
    """The lattice under the surface heights ``surface_z_m`` (nx, ny) (absolute z in
    W, m) of the columns at x_m (nx,) by y_m (ny,) (m, uniformly spaced, ascending,
    nx, ny >= 3), with grid levels from ``base_z_m`` (m) every ``level_spacing_m``
    (m); see the module docstring for the rules. Raises ValueError naming the bad
    argument, its value and what is allowed."""
    x_m = validate_grid_axis("x_m", x_m, 3)
    y_m = validate_grid_axis("y_m", y_m, 3)
    h = _validated_heights(surface_z_m, (len(x_m), len(y_m)), base_z_m, level_spacing_m)
    nx, ny = h.shape

    levels_below = np.ceil((h - base_z_m) / level_spacing_m - LEVEL_TOLERANCE)
    # A surface within the tolerance above the base still has the base level below it.
    levels_below = np.maximum(levels_below, 1.0)
    if levels_below.sum() + h.size > MAX_MASSES:  # checked in float, before any overflow
        raise ValueError(f"level_spacing_m = {level_spacing_m!r}: gives "
                         f"{levels_below.sum() + h.size:.3g} masses under surface_z_m; at most "
                         f"{MAX_MASSES} are allowed")
    count_below = levels_below.astype(np.int64)
    column_count = count_below + 1
    counts = column_count.ravel()  # x-major, as the masses are numbered
    starts = np.cumsum(counts) - counts
    surface = starts + counts - 1
    n = int(counts.sum())

    column = np.repeat(np.arange(nx * ny), counts)
    level = np.arange(n) - starts[column]
    h_flat = h.ravel()
    z = base_z_m + (level * (h_flat[column] - base_z_m)) / count_below.ravel()[column]
    z[surface] = h_flat  # exactly h, whatever the rounding above
    ix, iy = np.divmod(column, ny)
    positions = np.column_stack([x_m[ix], y_m[iy], z])

    links = _links(nx, ny, starts, counts, surface, h_flat, z)
    rest_lengths = np.linalg.norm(positions[links[:, 1]] - positions[links[:, 0]], axis=1)
    if not np.all(rest_lengths > 0):
        i, j = links[np.flatnonzero(rest_lengths <= 0)[0]]
        raise ValueError(f"masses {i} and {j} coincide at {positions[i]} m: surface_z_m is too "
                         f"close to base_z_m = {base_z_m!r} for float64 to separate them")

    fixed = (level == 0) | (ix == 0) | (ix == nx - 1) | (iy == 0) | (iy == ny - 1)
    return Lattice(x_m=x_m, y_m=y_m, positions_m=positions, fixed=fixed, links=links,
                   rest_lengths_m=rest_lengths, column_start=starts.reshape(nx, ny),
                   column_count=column_count, surface=surface.reshape(nx, ny),
                   surface_triangles=_surface_triangles(surface.reshape(nx, ny)))


def _validated_heights(surface_z_m, shape, base_z_m, level_spacing_m) -> np.ndarray:
    if not (isinstance(base_z_m, (int, float, np.integer, np.floating))
            and np.isfinite(base_z_m)):
        raise ValueError(f"base_z_m = {base_z_m!r}: must be a finite height (m)")
    if not (isinstance(level_spacing_m, (int, float, np.integer, np.floating))
            and np.isfinite(level_spacing_m) and level_spacing_m > 0):
        raise ValueError(f"level_spacing_m = {level_spacing_m!r}: must be a finite length > 0 (m)")
    h = np.asarray(surface_z_m, dtype=float)
    if h.shape != shape:
        raise ValueError(f"surface_z_m has shape {h.shape}: must be (len(x_m), len(y_m)) = {shape}")
    bad = np.argwhere(~np.isfinite(h))
    if len(bad):
        i, j = bad[0]
        raise ValueError(f"surface_z_m[{i}, {j}] = {float(h[i, j])!r}: must be finite")
    bad = np.argwhere(h <= base_z_m)
    if len(bad):
        i, j = bad[0]
        raise ValueError(f"surface_z_m[{i}, {j}] = {float(h[i, j])!r}: must be above base_z_m = "
                         f"{base_z_m!r}")
    return h


def _ragged_arange(lows: np.ndarray, lengths: np.ndarray):
    """The concatenation of arange(lows[k], lows[k] + lengths[k]) over k, and for each
    of its entries the k it came from."""
    owner = np.repeat(np.arange(len(lengths)), lengths)
    offsets = np.arange(owner.size) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    return lows[owner] + offsets, owner


def _adjacent_columns(nx: int, ny: int, a: int, b: int):
    """Flat indices of the column pairs (A, B) with B = A + (a, b), both on the grid."""
    ix = np.arange(max(0, -a), nx - max(0, a))
    iy = np.arange(max(0, -b), ny - max(0, b))
    first = (ix[:, None] * ny + iy[None, :]).ravel()
    return first, first + a * ny + b


def _links(nx, ny, starts, counts, surface, h, z) -> np.ndarray:
    """(m, 2) unique sorted links from the three phases; arguments flat over columns
    (x-major) except z, per mass."""
    # Phase 1, vertical neighbours: every mass but a surface vertex to the one above.
    below = np.setdiff1d(np.arange(len(z)), surface, assume_unique=True)
    ends = [(below, below + 1)]
    for a, b in HALF_NEIGHBOURHOOD:
        first, second = _adjacent_columns(nx, ny, a, b)
        # Phase 1, neighbours in the adjacent column one level down, level, or up.
        for c in (-1, 0, 1):
            low = max(0, -c)
            lengths = np.maximum(np.minimum(counts[first], counts[second] - c) - low, 0)
            j, pair = _ragged_arange(np.full(len(first), low), lengths)
            ends.append((starts[first][pair] + j, starts[second][pair] + j + c))
        # Phase 2.
        ends.append((surface[first], surface[second]))
        # Phase 3, from the higher column of each pair to the lower one's surface vertex.
        higher = np.where(h[first] > h[second], first, second)
        lower = np.where(h[first] > h[second], second, first)
        uneven = h[first] != h[second]
        higher, lower = higher[uneven], lower[uneven]
        mass, pair = _ragged_arange(starts[higher], counts[higher] - 1)
        above = z[mass] > h[lower][pair]
        ends.append((mass[above], surface[lower][pair][above]))

    i = np.concatenate([e[0] for e in ends])
    j = np.concatenate([e[1] for e in ends])
    n = len(z)
    # One key per unordered pair: np.unique then both removes the repeats of pairs
    # several rules link and sorts the rows lexicographically.
    keys = np.unique(np.minimum(i, j) * n + np.maximum(i, j))
    return np.column_stack([keys // n, keys % n]).astype(np.int64)


def _surface_triangles(surface: np.ndarray) -> np.ndarray:
    """Two triangles per grid cell, split along its (ix, iy)-(ix+1, iy+1) diagonal,
    counter-clockwise seen from +z (x right, y up)."""
    v00, v10 = surface[:-1, :-1], surface[1:, :-1]
    v11, v01 = surface[1:, 1:], surface[:-1, 1:]
    triangles = np.stack([np.stack([v00, v10, v11], axis=-1),
                          np.stack([v00, v11, v01], axis=-1)], axis=2)
    return triangles.reshape(-1, 3).astype(np.int64)
