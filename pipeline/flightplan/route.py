"""Ordering coverage patterns into a route, and cutting the route into sorties.

The UAS paper visits holes greedily, nearest next ([UAS] section 4). That is the
baseline here (:func:`greedy_route`); :func:`improve_route` then applies 2-opt
(reverse a run of patterns, each flown backwards), or-opt (move a run of one to
three patterns elsewhere, possibly reversed) and a per-pattern choice of entry
corner and direction, until nothing improves; finally the entries are chosen
exactly for the order found (a 4-state dynamic programme). Every move is
accepted only if it shortens the route, so the result is never longer than
the greedy route.

A pattern can be flown four ways (:func:`pattern_variants`): from its first or
its last lane, with the first lane flown forwards or backwards. Flying a variant
backwards is another variant (``reverse``), which is what makes 2-opt cheap.

:func:`split_sorties` cuts the improved route into sorties that each start and
end at home and last at most ``max_flight_time_s`` ("route first, cluster
second", Beasley 1983: an exact shortest-path split of the given order, fewest
sorties first, then the shortest total time).

Pure functions on coordinates in metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .coverage import CoveragePattern, Lane, Point2

__all__ = [
    "PatternEnds",
    "Visit",
    "greedy_route",
    "improve_route",
    "pattern_ends",
    "pattern_variants",
    "route_length",
    "split_sorties",
]


@dataclass(frozen=True)
class Visit:
    """One pattern in a route, flown as its ``variant``."""

    pattern: int
    variant: int


@dataclass(frozen=True)
class PatternEnds:
    """Where each variant of one pattern is entered and left (before/after the turnaround)."""

    entries: tuple[Point2, ...]
    exits: tuple[Point2, ...]
    reverse: tuple[int, ...]
    internal_m: float
    lanes: int = 1


def pattern_variants(pattern: CoveragePattern) -> list[tuple[Lane, ...]]:
    """The directed lane sequences a pattern can be flown in (4, or 2 for one lane)."""
    lanes = list(pattern.lanes)
    out: list[tuple[Lane, ...]] = []
    orders = [lanes] if len(lanes) == 1 else [lanes, lanes[::-1]]
    for order in orders:
        for first_backwards in (False, True):
            out.append(
                tuple(lane.reversed() if (i % 2 == 1) != first_backwards else lane for i, lane in enumerate(order))
            )
    return out


def pattern_ends(pattern: CoveragePattern) -> PatternEnds:
    """Entry and exit points of every variant, and which variant is its reverse."""
    t = pattern.turnaround_m
    entries, exits = [], []
    variants = pattern_variants(pattern)
    for lanes in variants:
        entries.append(_beyond(lanes[0].end, lanes[0].start, t))
        exits.append(_beyond(lanes[-1].start, lanes[-1].end, t))
    reverse = []
    for v in range(len(variants)):
        match = min(
            range(len(variants)),
            key=lambda w: math.dist(entries[w], exits[v]) + math.dist(exits[w], entries[v]),
        )
        reverse.append(match)
    internal = pattern.scan_length_m + pattern.turn_length_m
    return PatternEnds(tuple(entries), tuple(exits), tuple(reverse), internal, len(pattern.lanes))


def route_length(route: list[Visit], ends: list[PatternEnds], home: Point2, *, internal: bool = True) -> float:
    """Length of a closed route from home through the visits and back (metres)."""
    length, here = 0.0, home
    for visit in route:
        e = ends[visit.pattern]
        length += math.dist(here, e.entries[visit.variant]) + (e.internal_m if internal else 0.0)
        here = e.exits[visit.variant]
    return length + math.dist(here, home)


def greedy_route(ends: list[PatternEnds], home: Point2, patterns: list[int] | None = None) -> list[Visit]:
    """The paper's order: always fly to the nearest entry of a pattern not yet flown."""
    todo = set(range(len(ends)) if patterns is None else patterns)
    route, here = [], home
    while todo:
        best = min(
            ((math.dist(here, ends[p].entries[v]), p, v) for p in sorted(todo) for v in range(len(ends[p].entries))),
        )
        _, p, v = best
        route.append(Visit(p, v))
        here = ends[p].exits[v]
        todo.remove(p)
    return route


def improve_route(route: list[Visit], ends: list[PatternEnds], home: Point2, *, max_rounds: int = 100) -> list[Visit]:
    """2-opt, or-opt and entry changes until no move shortens the route.

    Never returns a longer route than the one given.
    """
    best = list(route)
    for _ in range(max_rounds):
        improved = _two_opt(best, ends, home) | _or_opt(best, ends, home) | _best_variants_locally(best, ends, home)
        if not improved:
            break
    exact = _best_variants_exactly(best, ends, home)
    if route_length(exact, ends, home) < route_length(best, ends, home) - 1e-9:
        best = exact
    return best


def split_sorties(
    route: list[Visit],
    ends: list[PatternEnds],
    home: Point2,
    *,
    lane_speed_m_s: float,
    transit_speed_m_s: float,
    setup_time_s: float,
    max_flight_time_s: float,
    acceleration_m_s2: float = math.inf,
) -> list[list[Visit]]:
    """Cut a route into sorties (each from and back to home) within the time limit.

    Raises
    ------
    ValueError
        If one pattern alone does not fit in a sortie (the caller splits it first).
    """
    n = len(route)
    if n == 0:
        return []

    def duration(i: int, j: int) -> float:  # visits i..j inclusive
        return sortie_duration(
            route[i : j + 1], ends, home, lane_speed_m_s, transit_speed_m_s, setup_time_s,
            acceleration_m_s2=acceleration_m_s2,
        )  # fmt: skip

    inf = (math.inf, math.inf)
    best: list[tuple[float, float]] = [(0.0, 0.0)] + [inf] * n
    previous = [0] * (n + 1)
    for j in range(n):
        for i in range(j, -1, -1):
            time = duration(i, j)
            if time > max_flight_time_s:
                if i == j:
                    raise ValueError(f"pattern {route[j].pattern} alone needs {time:.0f} s > {max_flight_time_s:.0f} s")
                break  # starting earlier only adds time
            candidate = (best[i][0] + 1, best[i][1] + time)
            if candidate < best[j + 1]:
                best[j + 1], previous[j + 1] = candidate, i
    sorties, j = [], n
    while j > 0:
        i = previous[j]
        sorties.append(route[i:j])
        j = i
    return sorties[::-1]


def sortie_duration(
    visits: list[Visit],
    ends: list[PatternEnds],
    home: Point2,
    lane_speed_m_s: float,
    transit_speed_m_s: float,
    setup_time_s: float,
    *,
    acceleration_m_s2: float = math.inf,
) -> float:
    """Seconds for one sortie: setup, transits at transit speed, patterns at lane speed, and turns.

    A turn between lanes has two right-angle corners, each costing the time to turn
    the velocity vector (``sqrt(2) v / a``); entering and leaving a pattern changes speed
    and direction (at most ``(v_transit + v_lane) / a``); the start from and stop at home
    ``v_transit / a`` each. The same model as the waypoints' flight time
    (:func:`pipeline.flightplan.clearance.flight_time_s`), without the climbs.
    """
    internal = sum(ends[v.pattern].internal_m for v in visits)
    transit = route_length(visits, ends, home, internal=False)
    corners = sum(2 * (ends[v.pattern].lanes - 1) for v in visits)
    changes = (
        corners * math.sqrt(2) * lane_speed_m_s
        + len(visits) * 2 * (transit_speed_m_s + lane_speed_m_s)
        + 2 * transit_speed_m_s
    )
    return setup_time_s + transit / transit_speed_m_s + internal / lane_speed_m_s + changes / acceleration_m_s2


def _beyond(origin: Point2, point: Point2, distance: float) -> Point2:
    """The point ``distance`` past ``point`` on the line from ``origin``."""
    length = math.dist(origin, point)
    if length == 0 or distance == 0:
        return point
    f = distance / length
    return (point[0] + (point[0] - origin[0]) * f, point[1] + (point[1] - origin[1]) * f)


def _entry(visit: Visit, ends: list[PatternEnds]) -> Point2:
    return ends[visit.pattern].entries[visit.variant]


def _exit(visit: Visit, ends: list[PatternEnds]) -> Point2:
    return ends[visit.pattern].exits[visit.variant]


def _flip(visit: Visit, ends: list[PatternEnds]) -> Visit:
    return Visit(visit.pattern, ends[visit.pattern].reverse[visit.variant])


def _two_opt(route: list[Visit], ends: list[PatternEnds], home: Point2) -> bool:
    """Reverse runs route[i..j] (each pattern flown backwards) while that shortens the route."""
    improved, n = False, len(route)
    for i in range(n):
        before = _exit(route[i - 1], ends) if i > 0 else home
        for j in range(i, n):
            after = _entry(route[j + 1], ends) if j + 1 < n else home
            old = math.dist(before, _entry(route[i], ends)) + math.dist(_exit(route[j], ends), after)
            new = math.dist(before, _exit(route[j], ends)) + math.dist(_entry(route[i], ends), after)
            if new < old - 1e-9:
                route[i : j + 1] = [_flip(v, ends) for v in reversed(route[i : j + 1])]
                improved = True
    return improved


def _or_opt(route: list[Visit], ends: list[PatternEnds], home: Point2) -> bool:
    """Move runs of 1 to 3 patterns to a better place, possibly reversed (O(1) gains)."""
    improved = False
    for size in (1, 2, 3):
        i = 0
        while i + size <= len(route):
            run = route[i : i + size]
            rest = route[:i] + route[i + size :]
            before = _exit(route[i - 1], ends) if i > 0 else home
            after = _entry(route[i + size], ends) if i + size < len(route) else home
            removal_gain = (
                math.dist(before, _entry(run[0], ends))
                + math.dist(_exit(run[-1], ends), after)
                - math.dist(before, after)
            )
            flipped = [_flip(v, ends) for v in reversed(run)]
            best_gain, best_route = 1e-9, None
            for k in range(len(rest) + 1):
                if k == i:
                    continue
                a = _exit(rest[k - 1], ends) if k > 0 else home
                b = _entry(rest[k], ends) if k < len(rest) else home
                for candidate in (run, flipped):
                    insertion = math.dist(a, _entry(candidate[0], ends)) + math.dist(_exit(candidate[-1], ends), b)
                    gain = removal_gain - (insertion - math.dist(a, b))
                    if gain > best_gain:
                        best_gain, best_route = gain, rest[:k] + candidate + rest[k:]
            if best_route is not None:
                route[:] = best_route
                improved = True
            i += 1
    return improved


def _best_variants_locally(route: list[Visit], ends: list[PatternEnds], home: Point2) -> bool:
    """Give each pattern its best entry for its neighbours."""
    improved = False
    for i, visit in enumerate(route):
        before = _exit(route[i - 1], ends) if i > 0 else home
        after = _entry(route[i + 1], ends) if i + 1 < len(route) else home
        e = ends[visit.pattern]

        costs = [math.dist(before, e.entries[v]) + math.dist(e.exits[v], after) for v in range(len(e.entries))]
        best = min(range(len(costs)), key=costs.__getitem__)
        if costs[best] < costs[visit.variant] - 1e-9:
            route[i] = Visit(visit.pattern, best)
            improved = True
    return improved


def _best_variants_exactly(route: list[Visit], ends: list[PatternEnds], home: Point2) -> list[Visit]:
    """For a fixed order, the entries that minimise the route (dynamic programme)."""
    if not route:
        return []
    e0 = ends[route[0].pattern]
    cost = [math.dist(home, p) for p in e0.entries]
    back: list[list[int]] = []
    for prev_visit, visit in zip(route, route[1:]):
        ep, ec = ends[prev_visit.pattern], ends[visit.pattern]
        new_cost, pointers = [], []
        for v in range(len(ec.entries)):
            k = min(range(len(cost)), key=lambda u: cost[u] + math.dist(ep.exits[u], ec.entries[v]))
            new_cost.append(cost[k] + math.dist(ep.exits[k], ec.entries[v]))
            pointers.append(k)
        back.append(pointers)
        cost = new_cost
    last = ends[route[-1].pattern]
    v = min(range(len(cost)), key=lambda u: cost[u] + math.dist(last.exits[u], home))
    variants = [v]
    for pointers in reversed(back):
        v = pointers[v]
        variants.append(v)
    variants.reverse()
    return [Visit(visit.pattern, variant) for visit, variant in zip(route, variants)]
