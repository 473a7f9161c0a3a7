"""Points -> per-pixel statistics: the hot kernel of stage 1, and the stage-2 merge.

For every pixel of a window this keeps the height-map statistics of the UAS
paper (hole-detection-and-reflight-uas.txt, "Preprocessing"): the maximum and
minimum z, the number of points, and the number of occupied voxels (distinct
``floor(z / voxel_height)`` levels), which equation 2 compares with the height
range to find vertical holes.

Counting *distinct* voxels exactly, whatever the tiling, needs more than a sum:
a voxel hit by two chunks (or two overlapping tiles) must count once. Within a
tile each pixel keeps a 64-bit mask of the voxel levels around the height of
its first point (``VOXEL_SPAN`` levels, cache-local like the other
accumulators); the rare levels outside that span go to an open-addressing hash
set of voxel keys. Both are compiled with numba and cost a few nanoseconds a
point, where ``np.unique`` per chunk would cost more than the LAZ decoding
itself (see docs/performance.md). Across tiles, the keys of pixels that another
tile's window also covers are kept and united in stage 2; every other pixel's
count is final after stage 1.

Pure: arrays in, arrays out; no I/O, no Dask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .grid import PixelWindow

#: A voxel key is ``grid_pixel << LEVEL_BITS | (level + LEVEL_OFFSET)``.
LEVEL_BITS = 20
LEVEL_OFFSET = 1 << (LEVEL_BITS - 1)
_LEVEL_MAX = (1 << LEVEL_BITS) - 1
_EMPTY_KEY = -1
#: Voxel levels a pixel's bit mask holds, centred on the level of its first point.
VOXEL_SPAN = 64
_SPAN_BELOW = VOXEL_SPAN // 2


#: The per-pixel statistics, and the type each is stored in.
STATISTIC_DTYPES: dict[str, type] = {
    "zmax": np.float32,
    "zmin": np.float32,
    "count": np.uint32,
    "voxels": np.uint16,
    "water": np.uint16,
    "source": np.uint16,
    "covered": np.uint16,
}
STATISTIC_NAMES = tuple(STATISTIC_DTYPES)
WATER_CLASS = 9
#: ASPRS noise classes (low and high noise): points a filter drops cover nothing.
NOISE_CLASSES = (7, 18)
#: ASPRS classes of the bare earth: ground, model key-points, water, rail, road surface.
BARE_EARTH_CLASSES = (2, 8, 9, 10, 11)


@dataclass
class PixelStatistics:
    """Height-map statistics of a window of the grid.

    Attributes
    ----------
    window : PixelWindow
        Where the arrays lie in the grid.
    zmax, zmin : ndarray of float32, shape (M, N)
        Highest and lowest point per pixel; NaN where the pixel is empty.
    count : ndarray of uint32, shape (M, N)
        Points per pixel.
    voxels : ndarray of uint16, shape (M, N)
        Occupied voxels per pixel.
    water : ndarray of uint16, shape (M, N)
        Points of the water class (ASPRS 9) per pixel: evidence for the cause of holes.
    source : ndarray of uint16, shape (M, N)
        The highest ``point_source_id + 1`` of the pixel's points (0: none); the
        flight line that covered it, whatever the order the points came in.
    covered : ndarray of uint16, shape (M, N)
        Points the class filter left out (not noise, not withheld) per pixel: a ground-only
        model's void under them is *covered* (by a building, by trees), not unmeasured.
    """

    window: PixelWindow
    zmax: np.ndarray
    zmin: np.ndarray
    count: np.ndarray
    voxels: np.ndarray
    water: np.ndarray
    source: np.ndarray
    covered: np.ndarray

    @classmethod
    def empty(cls, window: PixelWindow) -> PixelStatistics:
        shape = window.shape
        return cls(
            window=window,
            zmax=np.full(shape, np.nan, np.float32),
            zmin=np.full(shape, np.nan, np.float32),
            count=np.zeros(shape, np.uint32),
            voxels=np.zeros(shape, np.uint16),
            water=np.zeros(shape, np.uint16),
            source=np.zeros(shape, np.uint16),
            covered=np.zeros(shape, np.uint16),
        )

    def crop(self, window: PixelWindow) -> PixelStatistics:
        """The statistics of a sub-window (views, not copies)."""
        rows, cols = window.slices_within(self.window)
        return PixelStatistics(window, **{name: getattr(self, name)[rows, cols] for name in STATISTIC_NAMES})


@dataclass
class GroundSums:
    """Ground-class points (ASPRS 2, not withheld) of a window: the sum of their heights and their number per pixel.

    Kept with stage 1's statistics where holes are sought: a flight plan's take-off height is the
    ground's mean height at the take-off pixel (:mod:`pipeline.flightplan.takeoff`), and
    summing it while the points are decoded anyway spares the planner a second decoding of
    the files near the take-off. Every ground point counts, whatever the class filter keeps:
    the drone stands on the ground, not on the model.
    """

    window: PixelWindow
    height_sum: np.ndarray  # float64, (M, N)
    count: np.ndarray  # uint32, (M, N)

    @classmethod
    def empty(cls, window: PixelWindow) -> GroundSums:
        return cls(window, np.zeros(window.shape, np.float64), np.zeros(window.shape, np.uint32))

    def crop(self, window: PixelWindow) -> GroundSums:
        """The sums of a sub-window (views, not copies)."""
        rows, cols = window.slices_within(self.window)
        return GroundSums(window, self.height_sum[rows, cols], self.count[rows, cols])

    def mean_height(self) -> np.ndarray:
        """Mean ground height per pixel; NaN where no ground point fell."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.height_sum / np.maximum(self.count, 1), np.nan)


def merge_ground_sums(window: PixelWindow, parts: list[GroundSums]) -> GroundSums:
    """The ground sums of ``window`` from several tiles' (stage 2): sums and counts add, tiles overlapping or not."""
    merged = GroundSums.empty(window)
    for part in parts:
        overlap = part.window.intersection(window)
        if overlap.is_empty:
            continue
        src, dst = part.crop(overlap), merged.crop(overlap)
        dst.height_sum += src.height_sum
        dst.count += src.count
    return merged


#: The kernel's arguments where no ground is summed.
_NO_POINTS = np.zeros(0, bool)
_NO_SUMS = np.zeros(0, np.float64)
_NO_COUNTS = np.zeros(0, np.uint32)


class VoxelSet:
    """A growable open-addressing hash set of int64 voxel keys (the overflow of the bit masks)."""

    def __init__(self, capacity: int = 1 << 10) -> None:
        self.table = np.full(_next_power_of_two(capacity), _EMPTY_KEY, np.int64)
        self.size = 0

    def reserve(self, additional: int) -> None:
        """Make room for ``additional`` new keys at a load factor of at most 1/2."""
        needed = 2 * (self.size + additional)
        if needed > len(self.table):
            new = np.full(_next_power_of_two(needed), _EMPTY_KEY, np.int64)
            _rehash(self.table, new)
            self.table = new

    @property
    def room(self) -> int:
        """Keys that fit before the load factor passes 1/2."""
        return len(self.table) // 2 - self.size

    def keys(self) -> np.ndarray:
        return self.table[self.table != _EMPTY_KEY]


class HeightMapAccumulator:
    """Stage-1 accumulators of one tile's window: statistics plus distinct voxels.

    Parameters
    ----------
    window : PixelWindow
        The grid pixels the tile can touch.
    resolution, col_min, row_top, grid_width, offset
        The grid (see :class:`pipeline.grid.Grid`); a point goes to grid column
        ``floor(x / resolution + offset) - col_min`` and row
        ``row_top - floor(y / resolution + offset)``.
    voxel_height : float
        In z units.
    ground : bool
        Also sum the ground-class points' heights per pixel (:attr:`ground`), whatever the
        class filter keeps: the flight planner's take-off height, from the one decoding.
    """

    def __init__(
        self,
        window: PixelWindow,
        *,
        resolution: float,
        col_min: int,
        row_top: int,
        grid_width: int,
        voxel_height: float,
        offset: float = 0.0,
        ground: bool = False,
    ) -> None:
        self.statistics = PixelStatistics.empty(window)
        self.ground = GroundSums.empty(window) if ground else None
        self.voxel_base = np.zeros(window.shape, np.int64)
        self.voxel_bits = np.zeros(window.shape, np.uint64)
        self.overflow = VoxelSet()
        self._geometry = (float(resolution), int(col_min), int(row_top), int(grid_width), float(offset))
        self.voxel_height = float(voxel_height)

    @property
    def window(self) -> PixelWindow:
        return self.statistics.window

    def add(
        self,
        x: np.ndarray,
        y: np.ndarray,
        z: np.ndarray,
        keep: np.ndarray,
        *,
        water: np.ndarray | None = None,
        source: np.ndarray | None = None,
        ground: np.ndarray | None = None,
        scales: tuple[float, float, float] = (1.0, 1.0, 1.0),
        offsets: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> tuple[int, int]:
        """Bin a chunk of points, in place.

        Parameters
        ----------
        x, y, z : ndarray, shape (P,)
            Point coordinates: float64 in the survey CRS, or the integer
            coordinates of a LAS record with their ``scales`` and ``offsets``
            (the kernel then computes ``X * scale + offset`` exactly as laspy
            does, without materialising float arrays).
        keep : ndarray of bool, shape (P,)
            Points that passed the class/withheld filters.
        water : ndarray of bool, shape (P,), optional
            Points of the water class.
        source : ndarray of uint16, shape (P,), optional
            ``point_source_id`` of each point (the flight line).
        ground : ndarray of bool, shape (P,), optional
            Ground points (ASPRS 2, not withheld), summed into :attr:`ground` where the
            accumulator keeps it, kept by the filter or not.
        scales, offsets : tuple of 3 floats
            Of the integer coordinates; the defaults leave floats unchanged.

        Returns
        -------
        used, outside : int
            Points binned, and kept points that fell outside the window.
        """
        w = self.window
        s = self.statistics
        if water is None:
            water = np.zeros(len(x), bool)
        if source is None:
            source = np.full(len(x), np.iinfo(np.uint16).max, np.uint16)  # +1 wraps to 0: no line
        sums = self.ground
        if sums is None or ground is None:  # nothing summed: empty arrays tell the kernel
            ground, ground_sum, ground_count = _NO_POINTS, _NO_SUMS, _NO_COUNTS
        else:
            ground_sum, ground_count = sums.height_sum.reshape(-1), sums.count.reshape(-1)
        # the overflow set grows as it fills: the kernel stops before a point while the set is at
        # its load limit and goes on from there (a set sized for every point of a chunk to overflow
        # was 16 MB written a 650,000-point tile, against a few thousand keys)
        used = outside = start = 0
        while start < len(x):
            if self.overflow.room <= 0:
                self.overflow.reserve(max(self.overflow.size, 1 << 10))
            chunk_used, chunk_outside, added, start = _bin_points_kernel(
                x, y, z, keep, water, source, start, self.overflow.room,
                float(scales[0]), float(scales[1]), float(scales[2]),
                float(offsets[0]), float(offsets[1]), float(offsets[2]),
                *self._geometry,
                w.row_off, w.col_off, w.height, w.width,
                self.voxel_height,
                s.zmax.reshape(-1), s.zmin.reshape(-1), s.count.reshape(-1), s.voxels.reshape(-1),
                s.water.reshape(-1), s.source.reshape(-1),
                self.voxel_base.reshape(-1), self.voxel_bits.reshape(-1),
                self.overflow.table,
                ground, ground_sum, ground_count,
            )  # fmt: skip
            self.overflow.size += added
            used, outside = used + chunk_used, outside + chunk_outside
        return int(used), int(outside)

    def add_counts(
        self,
        name: str,
        x: np.ndarray,
        y: np.ndarray,
        which: np.ndarray,
        *,
        scales: tuple[float, float, float] = (1.0, 1.0, 1.0),
        offsets: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        """Add, per pixel, the points ``which`` of a chunk to the count statistic ``name`` (``covered``, ``water``).

        For points the rasters leave out: what they tell is evidence, not height.
        """
        resolution, col_min, row_top, _, lattice_offset = self._geometry
        w = self.window
        px = x[which] * scales[0] + offsets[0]
        py = y[which] * scales[1] + offsets[1]
        rows = row_top - np.floor(py / resolution + lattice_offset).astype(np.int64) - w.row_off
        cols = np.floor(px / resolution + lattice_offset).astype(np.int64) - col_min - w.col_off
        inside = (rows >= 0) & (rows < w.height) & (cols >= 0) & (cols < w.width)
        counts = np.bincount(rows[inside] * w.width + cols[inside], minlength=w.height * w.width)
        target = getattr(self.statistics, name).reshape(-1)
        target[:] = np.minimum(target + counts, 65535)

    def voxel_keys(self, windows: tuple[PixelWindow, ...]) -> np.ndarray:
        """Sorted distinct voxel keys of the pixels inside ``windows`` (shared with other tiles)."""
        grid_width = self._geometry[3]
        parts = [keys_in_windows(self.overflow.keys(), windows, grid_width)]
        for window in windows:
            overlap = window.intersection(self.window)
            if overlap.is_empty:
                continue
            sl = overlap.slices_within(self.window)
            bits = np.ascontiguousarray(self.voxel_bits[sl]).reshape(-1)
            base = self.voxel_base[sl].reshape(-1)
            occupied = bits != 0
            if not occupied.any():
                continue
            rows, cols = np.divmod(np.flatnonzero(occupied), overlap.width)
            pixel = (rows + overlap.row_off) * grid_width + (cols + overlap.col_off)
            set_bits = np.unpackbits(bits[occupied].view(np.uint8).reshape(-1, 8), axis=1, bitorder="little")
            which, bit = np.nonzero(set_bits)
            levels = base[occupied][which] + bit + LEVEL_OFFSET
            parts.append((pixel[which] << LEVEL_BITS) | np.clip(levels, 0, _LEVEL_MAX))
        return np.unique(np.concatenate(parts))


@dataclass(frozen=True)
class PointFilter:
    """Which points enter the rasters (from ``[filter]``, :func:`pipeline.parameters.read_params`)."""

    drop_classes: tuple[int, ...] = (7, 18)
    keep_classes: tuple[int, ...] = ()
    drop_withheld: bool = True

    @property
    def filters_classes(self) -> bool:
        """Whether the filter leaves out more than noise: the points it drops then cover the ground."""
        return bool(self.keep_classes) or bool(set(self.drop_classes) - set(NOISE_CLASSES))

    @property
    def bare_earth(self) -> bool:
        """Whether only bare-earth classes (``BARE_EARTH_CLASSES``) are kept: a terrain model (DTM),
        with no building, tree or other object in it whose top could hide the ground beside it."""
        kept = set(self.keep_classes) - set(self.drop_classes)
        return bool(kept) and kept <= set(BARE_EARTH_CLASSES)


def point_filter_mask(
    classification: np.ndarray,
    withheld: np.ndarray,
    *,
    drop_classes: tuple[int, ...],
    keep_classes: tuple[int, ...],
    drop_withheld: bool,
) -> np.ndarray:
    """Which points enter the rasters: a 256-entry lookup on the class, and the withheld flag."""
    allowed = np.zeros(256, bool)
    if keep_classes:
        allowed[list(keep_classes)] = True
    else:
        allowed[:] = True
    allowed[list(drop_classes)] = False
    keep = allowed[classification]
    if drop_withheld:
        keep &= ~withheld
    return keep


def removed_by_class_filter(
    classification: np.ndarray, withheld: np.ndarray, keep: np.ndarray, *, filters_classes: bool
) -> np.ndarray | None:
    """The points the class filter left out that are neither noise nor withheld (None: there are none).

    ``filters_classes``: whether the filter leaves out anything but noise (a ground-only model).
    Water points among them are evidence of water, not of a cover (:func:`removed_water`).
    """
    if not filters_classes:
        return None
    noise = np.zeros(256, bool)
    noise[list(NOISE_CLASSES)] = True
    removed = ~keep & ~withheld & ~noise[classification]
    return removed if removed.any() else None


def keys_in_windows(keys: np.ndarray, windows: tuple[PixelWindow, ...], grid_width: int) -> np.ndarray:
    """The sorted subset of voxel keys whose pixel lies in any of ``windows``."""
    if len(keys) == 0 or not windows:
        return np.empty(0, np.int64)
    pixel = keys >> LEVEL_BITS
    rows, cols = np.divmod(pixel, grid_width)
    inside = np.zeros(len(keys), bool)
    for w in windows:
        inside |= (rows >= w.row_off) & (rows < w.row_end) & (cols >= w.col_off) & (cols < w.col_end)
    return np.sort(keys[inside])


def shared_pixel_mask(window: PixelWindow, tile_windows: list[PixelWindow] | tuple[PixelWindow, ...]) -> np.ndarray:
    """Pixels of ``window`` that two or more tile windows cover."""
    coverage = np.zeros(window.shape, np.uint16)
    for w in tile_windows:
        overlap = w.intersection(window)
        if not overlap.is_empty:
            coverage[overlap.slices_within(window)] += 1
    return coverage >= 2


def merge_statistics(
    window: PixelWindow,
    parts: list[tuple[PixelStatistics, np.ndarray]],
    *,
    shared: np.ndarray,
    grid_width: int,
) -> PixelStatistics:
    """Merge the statistics several tiles hold for one window (stage 2).

    Parameters
    ----------
    window : PixelWindow
        The window to produce (a cell and its halo).
    parts : list of (PixelStatistics, keys)
        Each tile's statistics (any window overlapping ``window``) and its sorted
        voxel keys of shared pixels.
    shared : ndarray of bool, shape of ``window``
        Pixels covered by more than one tile window: their voxel count comes
        from the union of keys, every other pixel's from the one tile covering it.
    grid_width : int
        To decode pixel positions from keys.
    """
    merged = PixelStatistics.empty(window)
    key_parts = []
    for stats, keys in parts:
        overlap = stats.window.intersection(window)
        if overlap.is_empty:
            continue
        src = stats.crop(overlap)
        dst = merged.crop(overlap)
        np.fmax(dst.zmax, src.zmax, out=dst.zmax)
        np.fmin(dst.zmin, src.zmin, out=dst.zmin)
        dst.count += src.count
        dst.water += src.water
        np.maximum(dst.source, src.source, out=dst.source)
        dst.covered[...] = np.minimum(dst.covered.astype(np.uint32) + src.covered, 65535)
        local_shared = shared[overlap.slices_within(window)]
        dst.voxels += np.where(local_shared, 0, src.voxels).astype(np.uint16)
        if len(keys):
            key_parts.append(keys_in_windows(keys, (overlap,), grid_width))
    if key_parts:
        keys = np.unique(np.concatenate(key_parts))
        rows, cols = np.divmod(keys >> LEVEL_BITS, grid_width)
        local = (rows - window.row_off) * window.width + (cols - window.col_off)
        union_counts = np.bincount(local, minlength=window.height * window.width).reshape(window.shape)
        merged.voxels += np.where(shared, union_counts, 0).astype(np.uint16)
    return merged


# -- compiled kernels --------------------------------------------------------------------


def _next_power_of_two(n: int) -> int:
    return 1 << max(4, int(n - 1).bit_length())


@numba.njit(cache=True, nogil=True, inline="always")
def _slot(key, mask):
    """fmix64 of MurmurHash3: voxel keys are highly structured, so mix every bit."""
    h = np.uint64(key)
    h ^= h >> np.uint64(33)
    h *= np.uint64(0xFF51AFD7ED558CCD)
    h ^= h >> np.uint64(33)
    h *= np.uint64(0xC4CEB9FE1A85EC53)
    h ^= h >> np.uint64(33)
    return np.int64(h & np.uint64(mask))


@numba.njit(cache=True, nogil=True)
def _insert(table, key):
    """Insert ``key``; return True if it was not there yet (linear probing)."""
    mask = len(table) - 1
    slot = _slot(key, mask)
    while True:
        current = table[slot]
        if current == key:
            return False
        if current == -1:
            table[slot] = key
            return True
        slot = (slot + 1) & mask


@numba.njit(cache=True, nogil=True)
def _rehash(old, new):
    for i in range(len(old)):
        if old[i] != -1:
            _insert(new, old[i])


@numba.njit(cache=True, nogil=True)
def _bin_points_kernel(
    x, y, z, keep, water, source, start, room,
    scale_x, scale_y, scale_z, offset_x, offset_y, offset_z,
    resolution, col_min, row_top, grid_width, lattice_offset,
    win_row_off, win_col_off, win_height, win_width,
    voxel_height,
    zmax, zmin, count, voxels, water_count, source_max, voxel_base, voxel_bits,
    table,
    ground, ground_sum, ground_count,
):  # fmt: skip
    used = 0
    outside = 0
    added = 0
    summing = len(ground_sum) > 0
    for i in range(start, len(x)):
        if added >= room:  # the overflow set at its load limit: the caller grows it and goes on from point i
            return used, outside, added, i
        on_ground = summing and ground[i]
        if not keep[i] and not on_ground:
            continue
        px = np.float64(x[i]) * scale_x + offset_x
        py = np.float64(y[i]) * scale_y + offset_y
        pz = np.float64(z[i]) * scale_z + offset_z
        col = np.int64(np.floor(px / resolution + lattice_offset)) - col_min
        row = row_top - np.int64(np.floor(py / resolution + lattice_offset))
        local_row = row - win_row_off
        local_col = col - win_col_off
        if local_row < 0 or local_row >= win_height or local_col < 0 or local_col >= win_width:
            if keep[i]:
                outside += 1
            continue
        p = local_row * win_width + local_col
        if on_ground:
            ground_sum[p] += pz
            ground_count[p] += 1
            if not keep[i]:
                continue
        height = np.float32(pz)
        level = np.int64(np.floor(pz / voxel_height))
        if level < -LEVEL_OFFSET:
            level = -LEVEL_OFFSET
        elif level > _LEVEL_MAX - LEVEL_OFFSET:
            level = _LEVEL_MAX - LEVEL_OFFSET
        used += 1
        if water[i] and water_count[p] < 65535:
            water_count[p] += 1
        line = np.uint16(source[i] + np.uint16(1))
        if line > source_max[p]:
            source_max[p] = line
        if count[p] == 0:
            count[p] = 1
            zmax[p] = height
            zmin[p] = height
            voxel_base[p] = level - _SPAN_BELOW
            voxel_bits[p] = np.uint64(1) << np.uint64(_SPAN_BELOW)
            voxels[p] = 1
            continue
        count[p] += 1
        if height > zmax[p]:
            zmax[p] = height
        if height < zmin[p]:
            zmin[p] = height
        offset = level - voxel_base[p]
        if offset >= 0 and offset < VOXEL_SPAN:
            bit = np.uint64(1) << np.uint64(offset)
            if (voxel_bits[p] & bit) == 0:
                voxel_bits[p] |= bit
                if voxels[p] < 65535:
                    voxels[p] += 1
        else:
            key = ((row * grid_width + col) << LEVEL_BITS) | (level + LEVEL_OFFSET)
            if _insert(table, key):
                added += 1
                if voxels[p] < 65535:
                    voxels[p] += 1
    return used, outside, added, len(x)
