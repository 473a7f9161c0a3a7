"""Pictures for the maps: the shaded relief of a DSM and a standard-library PNG encoder."""

from __future__ import annotations

import base64
import math
import struct
import zlib

import numpy as np

#: Elevation ramp of the DSM (fraction of the 2-98 % height range -> RGB), shaded by the hillshade.
_RAMP = (
    (0.00, (46, 112, 72)),
    (0.30, (150, 182, 96)),
    (0.55, (233, 217, 148)),
    (0.80, (186, 134, 86)),
    (1.00, (246, 244, 240)),
)


def shaded_relief(
    dsm: np.ndarray,
    *,
    pixel_size: tuple[float, float],
    height_range: tuple[float, float] | None = None,
    azimuth_deg: float = 315.0,
    altitude_deg: float = 45.0,
) -> np.ndarray:
    """An RGBA image of a DSM: heights coloured on an elevation ramp, shaded by a hillshade.

    Parameters
    ----------
    dsm : ndarray of shape (M, N)
        Heights, north up; NaN where there is no value (transparent in the image).
    pixel_size : tuple of float
        ``(dx, dy)`` pixel size in the CRS unit.
    height_range : tuple of float, optional
        Heights at the ends of the ramp (default: the 2nd and 98th percentiles).
    azimuth_deg, altitude_deg : float
        The light's direction (clockwise from north) and elevation.

    Returns
    -------
    ndarray of shape (M, N, 4), uint8

    Notes
    -----
    A coarse map flattens slopes: the heights are exaggerated by the square root of the
    pixel size (1 to 5 times) so a 100 km survey still shows its relief.
    """
    z = np.asarray(dsm, dtype=np.float64)
    valid = np.isfinite(z)
    rgba = np.zeros((*z.shape, 4), np.uint8)
    if not valid.any():
        return rgba
    if not valid.all():  # nearest valid height under the gaps, so their edges cast no shadow
        from scipy import ndimage as ndi

        index = ndi.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        z = z[tuple(index)]
    lo, hi = height_range if height_range is not None else _height_range(dsm)
    dx, dy = (abs(float(p)) for p in pixel_size)
    exaggeration = min(5.0, max(1.0, math.sqrt(max(dx, dy))))
    if min(z.shape) >= 2:
        d_row, d_col = np.gradient(z * exaggeration, dy, dx)
    else:
        d_row = d_col = np.zeros_like(z)
    dz_east, dz_north = d_col, -d_row
    az, alt = math.radians(azimuth_deg), math.radians(altitude_deg)
    light = (math.sin(az) * math.cos(alt), math.cos(az) * math.cos(alt), math.sin(alt))
    shade = (-dz_east * light[0] - dz_north * light[1] + light[2]) / np.sqrt(1 + dz_east**2 + dz_north**2)
    shade = np.clip(shade, 0, 1) / max(math.sin(alt), 1e-6)  # flat ground: 1
    t = np.clip((z - lo) / (hi - lo), 0, 1) if hi > lo else np.full(z.shape, 0.5)
    fractions = [f for f, _ in _RAMP]
    for channel in range(3):
        colour = np.interp(t, fractions, [c[channel] for _, c in _RAMP])
        rgba[..., channel] = np.clip(colour * (0.35 + 0.65 * np.clip(shade, 0, 1.25)), 0, 255).astype(np.uint8)
    rgba[..., 3] = np.where(valid, 255, 0)
    return rgba


def encode_png(pixels: np.ndarray) -> bytes:
    """PNG bytes of an 8-bit image: (M, N) grey, (M, N, 2) grey + alpha, (M, N, 3) RGB or (M, N, 4) RGBA.

    Standard library only (``zlib``, ``struct``); every row uses the "up" filter, which
    suits smooth shaded relief.
    """
    a = np.asarray(pixels)
    if a.dtype != np.uint8:
        raise ValueError(f"encode_png needs uint8 pixels, got {a.dtype}")
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 2, 3, 4) or min(a.shape[:2]) < 1:
        raise ValueError(f"encode_png needs an (M, N) or (M, N, 1-4) image, got shape {pixels.shape}")
    height, width, channels = a.shape
    rows = np.ascontiguousarray(a).reshape(height, width * channels)
    up = rows.copy()
    up[1:] -= rows[:-1]  # uint8 arithmetic wraps modulo 256, as PNG wants
    raw = np.hstack([np.full((height, 1), 2, np.uint8), up]).tobytes()
    colour_type = {1: 0, 2: 4, 3: 2, 4: 6}[channels]
    header = struct.pack(">IIBBBBB", width, height, 8, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, 1)) + _chunk(b"IEND", b"")
    )


def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _height_range(dsm: np.ndarray) -> tuple[float, float]:
    finite = dsm[np.isfinite(dsm)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(finite, [2, 98])
    return float(lo), float(hi if hi > lo else lo + 1.0)
