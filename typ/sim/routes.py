"""Closed driving loops around blocks of the road grid, so vehicles never leave the road.

A loop follows one lane around the rectangle spanned by two roads each way, turning at the
corners on quarter circles. Traffic keeps right, so a counter-clockwise loop drives on the
outside of the rectangle of road centre lines and turns left; a clockwise one drives inside
and turns right. All lanes turning at one corner share the arc centre, so their arcs are
concentric and never cross each other.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from typ.sim.town import Town


@dataclass(frozen=True)
class LoopRoute:
    """Rounded rectangle ``[x0, x1] x [y0, y1]`` (lane centre lines, metres) with corner ``radius``.

    Arc length s starts at the left end of the bottom straight; ``ccw`` sets the direction.
    """

    x0: float
    x1: float
    y0: float
    y1: float
    radius: float
    ccw: bool

    @property
    def length(self) -> float:
        return 2.0 * (self.x1 - self.x0 + self.y1 - self.y0) - 8.0 * self.radius + 2.0 * np.pi * self.radius

    def pose_at(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arc length ``s`` (any shape, wraps around) -> world ``x, y, yaw`` (yaw rad, direction of travel)."""
        s = np.mod(np.asarray(s, dtype=np.float64), self.length)
        if self.ccw:
            return self._ccw(s)
        x, y, yaw = self._ccw(np.mod(self.length - s, self.length))
        return x, y, np.mod(yaw + 2.0 * np.pi, 2.0 * np.pi) - np.pi

    def _ccw(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r = self.radius
        lx, ly = self.x1 - self.x0 - 2 * r, self.y1 - self.y0 - 2 * r
        arc = 0.5 * np.pi * r
        # Pieces in travel order: straight east, arc, north, arc, west, arc, south, arc.
        lengths = np.array([lx, arc, ly, arc, lx, arc, ly, arc])
        starts = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
        k = np.clip(np.searchsorted(starts, s, side="right") - 1, 0, 7)
        u = s - starts[k]
        straight_start = np.array([[self.x0 + r, self.y0], [self.x1, self.y0 + r],
                                   [self.x1 - r, self.y1], [self.x0, self.y1 - r]])
        heading = np.array([0.0, 0.5 * np.pi, np.pi, -0.5 * np.pi])
        centre = np.array([[self.x1 - r, self.y0 + r], [self.x1 - r, self.y1 - r],
                           [self.x0 + r, self.y1 - r], [self.x0 + r, self.y0 + r]])
        side = k // 2
        is_arc = (k % 2) == 1
        # Straights.
        x = straight_start[side, 0] + u * np.cos(heading[side])
        y = straight_start[side, 1] + u * np.sin(heading[side])
        yaw = heading[side]
        # Arcs start at angle heading - 90 deg around their centre.
        phi = heading[side] - 0.5 * np.pi + u / r
        x = np.where(is_arc, centre[side, 0] + r * np.cos(phi), x)
        y = np.where(is_arc, centre[side, 1] + r * np.sin(phi), y)
        yaw = np.where(is_arc, phi + 0.5 * np.pi, yaw)
        return x, y, np.mod(yaw + np.pi, 2.0 * np.pi) - np.pi


def town_routes(town: Town) -> list[LoopRoute]:
    """Every loop of the town: each rectangle of two roads each way, both directions, every lane."""
    style = town.style
    # Arc centres sit this far into the block from the crossing of the road centre lines:
    # right turns well clear of the kerb corner, left turns through the middle of the crossing.
    right_turn_centre = style.road_half_width + 2.5
    left_turn_centre = 3.0
    routes = []
    for ax0, ax1 in combinations(town.road_x, 2):
        for ay0, ay1 in combinations(town.road_y, 2):
            for o in style.lane_offsets:
                routes.append(LoopRoute(ax0 - o, ax1 + o, ay0 - o, ay1 + o, left_turn_centre + o, True))
                routes.append(LoopRoute(ax0 + o, ax1 - o, ay0 + o, ay1 - o, right_turn_centre - o, False))
    return routes
