"""Still water besides the river: lakes and a canal between quays (analytic, in local coordinates).

Like :class:`~pipeline.synth.scene.River`, each is a pure function of ``(u, v)``:
where the water is, its (flat) level, and how it shapes the ground around it, so a
window of the fine grid can be sampled on its own (:meth:`Scene.rasterize`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .shore import blend_to_shore
from .spec import RIVER_BANK_WIDTH_M


@dataclass(frozen=True, eq=False)
class Lakes:
    """Elliptic lakes with flat water, as parallel arrays (one entry per lake).

    The ground is blended down to a shore just above the water (as beside the
    river), so each shore is a contour line. Lakes never overlap each other's banks.

    Attributes
    ----------
    center_u, center_v : ndarray
        Centre, local metres.
    semi_major, semi_minor : ndarray
        Semi-axes of the water's ellipse.
    angle : ndarray
        Direction of the major axis, radians counter-clockwise from east.
    water_level : ndarray
        Absolute height of each lake's water surface.
    bank_width : float
        Width over which the terrain is blended down to the shore.
    """

    center_u: np.ndarray
    center_v: np.ndarray
    semi_major: np.ndarray
    semi_minor: np.ndarray
    angle: np.ndarray
    water_level: np.ndarray
    bank_width: float = RIVER_BANK_WIDTH_M

    def __len__(self) -> int:
        return len(self.center_u)

    def _radial(self, index: int, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance from the centre and the ellipse's normalised radius (1 on the shore) at ``(u, v)``."""
        du, dv = np.asarray(u) - self.center_u[index], np.asarray(v) - self.center_v[index]
        cos, sin = np.cos(self.angle[index]), np.sin(self.angle[index])
        along, across = du * cos + dv * sin, -du * sin + dv * cos
        radius = np.hypot(along / self.semi_major[index], across / self.semi_minor[index])
        return np.hypot(du, dv), radius

    def is_water(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Whether ``(u, v)`` lies in some lake."""
        water = np.zeros(np.broadcast_shapes(np.shape(u), np.shape(v)), dtype=bool)
        for index in range(len(self)):
            water |= self._radial(index, u, v)[1] < 1.0
        return water

    def level(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Water level of the lake at ``(u, v)`` (NaN outside every lake)."""
        level = np.full(np.broadcast_shapes(np.shape(u), np.shape(v)), np.nan)
        for index in range(len(self)):
            level[self._radial(index, u, v)[1] < 1.0] = self.water_level[index]
        return level

    def shape_ground(self, ground: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Ground blended down to each shore, the lake bed 1 m under the water.

        The distance to the shore is measured along the ray from the centre
        (``|p| (1 - 1 / r)`` for a normalised radius ``r``): exact on the axes,
        smooth and growing outward everywhere, which is all the banks need.
        """
        shaped = np.asarray(ground, dtype=np.float64)
        for index in range(len(self)):
            distance_from_centre, radius = self._radial(index, u, v)
            if not np.any(radius < 1.0 + self.bank_width / self.semi_minor[index]):
                continue  # the window is beyond this lake's banks
            distance = distance_from_centre * (1.0 - 1.0 / np.maximum(radius, 1e-9))
            level = self.water_level[index]
            banks = np.where(
                distance < self.bank_width, blend_to_shore(shaped, distance, level, self.bank_width), shaped
            )
            shaped = np.where(radius < 1.0, level - 1.0, banks)
        return shaped

    @property
    def reach(self) -> np.ndarray:
        """Radius around each centre beyond which a lake leaves the ground untouched."""
        return self.semi_major + self.bank_width

    def polygons(self, step_deg: float = 3.0) -> list[np.ndarray]:
        """Each lake's water outline as an (N, 2) ring of local coordinates."""
        t = np.radians(np.arange(0.0, 360.0 + step_deg / 2, step_deg))
        rings = []
        for index in range(len(self)):
            a, b = self.semi_major[index] * np.cos(t), self.semi_minor[index] * np.sin(t)
            cos, sin = np.cos(self.angle[index]), np.sin(self.angle[index])
            ring = np.column_stack([self.center_u[index] + a * cos - b * sin, self.center_v[index] + a * sin + b * cos])
            ring[-1] = ring[0]
            rings.append(ring)
        return rings


@dataclass(frozen=True, eq=False)
class Canal:
    """A straight N-S canal between quay walls, crossing the scene, with a flat street beside it.

    Water where ``|u - center_u| < half_width``, at ``water_level``. Beyond it the
    ground is flat at the quay top (``water_level + quay_height``: a vertical quay
    wall) up to ``flat_half_width`` from the axis (the street and the canal-side
    buildings stand there), then blended to the terrain over ``bank_width``.
    """

    center_u: float
    half_width: float
    water_level: float
    quay_height: float
    flat_half_width: float
    street: float = 0.0  # between the quay edge and the facades of the canal-side buildings
    bank_width: float = RIVER_BANK_WIDTH_M

    @property
    def quay_z(self) -> float:
        return self.water_level + self.quay_height

    def is_water(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        shape = np.broadcast_shapes(np.shape(u), np.shape(v))
        return np.broadcast_to(np.abs(np.asarray(u) - self.center_u) < self.half_width, shape)

    def shape_ground(self, ground: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The quays and the street at ``quay_z``, blended to the terrain farther out.

        The ground is ``quay_z`` over the water too: a pulse aimed at a quay's fine cell
        returns from the top of the (vertical) quay wall wherever it lands in that cell,
        never from a canal bed 2-3 m lower that no pulse can reach.
        """
        offset = np.abs(np.asarray(u) - self.center_u)
        t = np.clip((offset - self.flat_half_width) / self.bank_width, 0.0, 1.0)
        smooth = t * t * (3.0 - 2.0 * t)
        return self.quay_z + (np.asarray(ground, dtype=np.float64) - self.quay_z) * smooth

    def polygon(self, v_min: float, v_max: float) -> np.ndarray:
        """The water outline between ``v_min`` and ``v_max`` as a closed (5, 2) ring of local coordinates."""
        west, east = self.center_u - self.half_width, self.center_u + self.half_width
        return np.array([[west, v_min], [east, v_min], [east, v_max], [west, v_max], [west, v_min]])
