"""The S-curve step of a wall ([WALL]): its residuals, their Jacobian and a bounded least-squares fit, compiled.

:func:`step_residuals` models a pixel's highest and lowest points across a straight height
step (module docstring of :mod:`pipeline.holes.walls`); :func:`bounded_least_squares` fits
its five parameters within bounds by Levenberg-Marquardt, with the soft-L1 loss on request,
in one compiled call (scipy's ``least_squares`` spent 3.7 ms a wall in its interpreter; this
0.5 ms). Pure numba kernels; :func:`pipeline.holes.walls.fit_wall` sets up the problem.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = [
    "LOGISTIC_NODES",
    "bounded_least_squares",
    "jacobian_at",
    "soft_l1_cost",
    "square_share_slopes",
    "step_jacobian",
    "step_residuals",
]


#: Equal-weight quadrature nodes of the standard logistic distribution (its deciles 1, 3,
#: 5, 7, 9): smoothing by the S-curve is the mean over these shifts.
LOGISTIC_NODES = np.log(np.array([0.1, 0.3, 0.5, 0.7, 0.9]) / (1 - np.array([0.1, 0.3, 0.5, 0.7, 0.9])))


@numba.njit(cache=True)
def step_residuals(
    params, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes
):  # pragma: no cover - compiled
    """Residuals of the S-curve step model ([WALL]) for :func:`fit_wall`, compiled.

    ``params`` = (phi, rho, low, high, log_width): the line ``x cos phi + y sin phi = rho``.
    Highest points follow ``low + step (1 - (1 - a)^k)``, lowest points ``low + step a^k``
    and empty pixels ``step a`` (they should be on the low side), with ``a`` the pixel's
    share on the high side.
    """
    phi, rho, low, high, log_width = params[0], params[1], params[2], params[3], params[4]
    c, s = math.cos(phi), math.sin(phi)
    u, v, width, step = abs(c), abs(s), math.exp(log_width), high - low
    n_high, n_low = len(x_high), len(x_low)
    out = np.empty(n_high + n_low + len(x_empty))
    share = square_share_kernel(x_high * c + y_high * s - rho, u, v, width, nodes)
    for i in range(n_high):
        out[i] = low + step * (1.0 - (1.0 - share[i]) ** k_high[i]) - z_high[i]
    share = square_share_kernel(x_low * c + y_low * s - rho, u, v, width, nodes)
    for i in range(n_low):
        out[n_high + i] = low + step * share[i] ** k_low[i] - z_low[i]
    share = square_share_kernel(x_empty * c + y_empty * s - rho, u, v, width, nodes)
    for i in range(len(x_empty)):
        out[n_high + n_low + i] = step * share[i]
    return out


@numba.njit(cache=True)
def step_jacobian(
    params, lower, upper, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes
):  # pragma: no cover - compiled
    """Jacobian of :func:`step_residuals` (see :func:`jacobian_at`), in one compiled call."""
    base = step_residuals(params, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes)
    return jacobian_at(
        params, base, lower, upper, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes
    )


@numba.njit(cache=True)
def jacobian_at(
    params, base, lower, upper, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes
):  # pragma: no cover - compiled
    """Jacobian of :func:`step_residuals` in one compiled call: analytic but for the wall's direction.

    ``low`` and ``high`` enter linearly; ``rho`` and ``log_width`` move every pixel's
    signed distance, whose effect on its share is the S-curve-smoothed trapezoid's
    density (:func:`square_share_slopes`). The direction ``phi`` also reshapes the
    trapezoid (``|cos phi|``, ``|sin phi|``): a forward difference, scipy's "2-point" rule
    (sqrt of machine epsilon, relative to the parameter), taken backwards where a forward
    step would leave the bounds. ``base``: the residuals at ``params``. One residual
    evaluation and the shares' slopes instead of five evaluations.
    """
    phi, rho, low, high, log_width = params[0], params[1], params[2], params[3], params[4]
    c, s = math.cos(phi), math.sin(phi)
    u, v, width, step = abs(c), abs(s), math.exp(log_width), high - low
    n_high, n_low, n_empty = len(x_high), len(x_low), len(x_empty)
    jacobian = np.empty((n_high + n_low + n_empty, 5))
    share, slope, node_slope = square_share_slopes(x_high * c + y_high * s - rho, u, v, width, nodes)
    for i in range(n_high):
        k = k_high[i]
        below = (1.0 - share[i]) ** (k - 1.0)  # d/da of 1 - (1 - a)^k is k (1 - a)^(k - 1)
        d_share = step * k * below
        jacobian[i, 1] = -d_share * slope[i]
        jacobian[i, 2] = below * (1.0 - share[i])
        jacobian[i, 3] = 1.0 - jacobian[i, 2]
        jacobian[i, 4] = d_share * width * node_slope[i]
    share, slope, node_slope = square_share_slopes(x_low * c + y_low * s - rho, u, v, width, nodes)
    for i in range(n_low):
        k = k_low[i]
        below = share[i] ** (k - 1.0)
        d_share = step * k * below
        row = n_high + i
        jacobian[row, 1] = -d_share * slope[i]
        jacobian[row, 3] = below * share[i]
        jacobian[row, 2] = 1.0 - jacobian[row, 3]
        jacobian[row, 4] = d_share * width * node_slope[i]
    share, slope, node_slope = square_share_slopes(x_empty * c + y_empty * s - rho, u, v, width, nodes)
    for i in range(n_empty):
        row = n_high + n_low + i
        jacobian[row, 1] = -step * slope[i]
        jacobian[row, 2] = -share[i]
        jacobian[row, 3] = share[i]
        jacobian[row, 4] = step * width * node_slope[i]
    h = 1.4901161193847656e-08 * max(1.0, abs(phi))
    if phi + h > upper[0]:
        h = -h
    shifted = params.copy()
    shifted[0] += h
    h = shifted[0] - phi  # the step actually taken, after rounding
    moved = step_residuals(shifted, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes)
    for i in range(len(base)):
        jacobian[i, 0] = (moved[i] - base[i]) / h
    return jacobian


def soft_l1_cost(residuals: np.ndarray, f_scale: float) -> float:
    """The cost least_squares(loss="soft_l1") reports for these residuals."""
    z = (residuals / f_scale) ** 2
    return float(0.5 * f_scale**2 * np.sum(2 * (np.sqrt(1 + z) - 1)))


#: Levenberg-Marquardt damping: start, growth on a rejected step, shrink on an accepted one.
_DAMPING_START, _DAMPING_UP, _DAMPING_DOWN = 1e-3, 4.0, 1.0 / 3.0
#: Relative tolerances on the cost's decrease, the step and the scaled gradient (1e-6: far
#: below the 0.2-pixel accuracy a wall needs).
_FTOL = _XTOL = _GTOL = 1e-6


@numba.njit(cache=True)
def loss_weights(fun, f_scale):  # pragma: no cover - compiled
    """sqrt(rho'(z)) per residual for the soft-L1 loss ``rho(z) = 2 (sqrt(1 + z) - 1)``, ``z = (f / f_scale)^2``."""
    weights = np.ones(len(fun))
    if f_scale > 0.0:
        for i in range(len(fun)):
            z = (fun[i] / f_scale) ** 2
            weights[i] = (1.0 + z) ** -0.25
    return weights


@numba.njit(cache=True)
def loss_cost(fun, f_scale):  # pragma: no cover - compiled
    """0.5 sum of squares (``f_scale`` 0), else the soft-L1 cost as scipy's least_squares reports it."""
    total = 0.0
    for i in range(len(fun)):
        if f_scale > 0.0:
            total += f_scale * f_scale * 2.0 * (math.sqrt(1.0 + (fun[i] / f_scale) ** 2) - 1.0)
        else:
            total += fun[i] * fun[i]
    return 0.5 * total


@numba.njit(cache=True)
def damped_step(normal, gradient, damping):  # pragma: no cover - compiled
    """Solve ``(N + damping diag(N)) d = -g`` by Cholesky; an all-NaN step when not positive definite."""
    n = len(gradient)
    a = normal.copy()
    for j in range(n):
        a[j, j] += damping * max(normal[j, j], 1e-12)
    lower = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            value = a[i, j]
            for k in range(j):
                value -= lower[i, k] * lower[j, k]
            if i == j:
                if not value > 0.0:
                    return np.full(n, np.nan)
                lower[i, i] = math.sqrt(value)
            else:
                lower[i, j] = value / lower[j, j]
    y = np.empty(n)
    for i in range(n):
        value = -gradient[i]
        for k in range(i):
            value -= lower[i, k] * y[k]
        y[i] = value / lower[i, i]
    step = np.empty(n)
    for i in range(n - 1, -1, -1):
        value = y[i]
        for k in range(i + 1, n):
            value -= lower[k, i] * step[k]
        step[i] = value / lower[i, i]
    return step


@numba.njit(cache=True)
def bounded_least_squares(
    x0, lower, upper, scale, f_scale, max_nfev,
    x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes,
):  # pragma: no cover - compiled  # fmt: skip
    """Minimise the step model's cost within the bounds: Levenberg-Marquardt, steps clipped to the box.

    Variables are scaled by ``scale`` (the size of a meaningful change of each); ``f_scale``
    > 0 fits the soft-L1 loss by reweighting the residuals and the Jacobian with
    sqrt(rho') at every iteration (the first-order part of scipy's loss scaling). Stops when
    the cost falls by less than ``_FTOL`` of itself, the scaled step is below ``_XTOL`` of the
    scaled parameters, or the largest projected scaled gradient below ``_GTOL`` (as scipy's);
    status 1, or 0 when ``max_nfev`` residual evaluations are spent (the best fit so far),
    -1 when the start gives no finite cost.
    """
    n = len(x0)
    x = x0.copy()
    fun = step_residuals(x, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes)
    cost = loss_cost(fun, f_scale)
    if not np.isfinite(cost):
        return x, fun, cost, -1
    nfev, damping = 1, _DAMPING_START
    while nfev < max_nfev:
        jacobian = jacobian_at(
            x, fun, lower, upper, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes
        )
        weights = loss_weights(fun, f_scale)
        normal = np.zeros((n, n))
        gradient = np.zeros(n)
        for i in range(len(fun)):
            w2 = weights[i] * weights[i]
            for a in range(n):
                ja = jacobian[i, a] * scale[a]
                gradient[a] += w2 * ja * fun[i]
                for b in range(a + 1):
                    normal[a, b] += w2 * ja * jacobian[i, b] * scale[b]
        for a in range(n):
            for b in range(a):
                normal[b, a] = normal[a, b]
        # a variable at a bound that the gradient pushes out of the box is held there (active set)
        largest = 0.0
        for a in range(n):
            held = (x[a] <= lower[a] and gradient[a] > 0.0) or (x[a] >= upper[a] and gradient[a] < 0.0)
            if held:
                gradient[a] = 0.0
                for b in range(n):
                    normal[a, b] = 0.0
                    normal[b, a] = 0.0
                normal[a, a] = 1.0
            else:
                largest = max(largest, abs(gradient[a]))
        if largest < _GTOL:
            return x, fun, cost, 1
        accepted = False
        while nfev < max_nfev:
            step = damped_step(normal, gradient, damping)
            if not np.isfinite(step).all():
                damping *= _DAMPING_UP
                if damping > 1e12:
                    return x, fun, cost, 1
                continue
            trial = np.empty(n)
            taken = np.empty(n)  # the scaled step after clipping to the box
            step_norm, x_norm = 0.0, 0.0
            for a in range(n):
                trial[a] = min(max(x[a] + step[a] * scale[a], lower[a]), upper[a])
                taken[a] = (trial[a] - x[a]) / scale[a]
                step_norm += taken[a] ** 2
                x_norm += (x[a] / scale[a]) ** 2
            # the decrease the Gauss-Newton model predicts for the step taken
            predicted = -(gradient @ taken + 0.5 * taken @ (normal @ taken))
            trial_fun = step_residuals(
                trial, x_high, y_high, k_high, z_high, x_low, y_low, k_low, z_low, x_empty, y_empty, nodes
            )
            nfev += 1
            trial_cost = loss_cost(trial_fun, f_scale)
            if np.isfinite(trial_cost) and trial_cost < cost:
                decrease = cost - trial_cost
                ratio = decrease / predicted if predicted > 0.0 else 0.0
                x, fun, cost = trial, trial_fun, trial_cost
                if ratio > 0.75:
                    damping = max(damping * _DAMPING_DOWN, 1e-12)
                elif ratio < 0.25:
                    damping *= 2.0
                accepted = True
                # as scipy's trf: a small decrease ends the search only where the model holds
                if (decrease < _FTOL * cost and ratio > 0.25) or math.sqrt(step_norm) < _XTOL * (
                    _XTOL + math.sqrt(x_norm)
                ):
                    return x, fun, cost, 1
                break
            damping *= _DAMPING_UP
            if damping > 1e12 or math.sqrt(step_norm) < _XTOL * (_XTOL + math.sqrt(x_norm)):
                return x, fun, cost, 1
        if not accepted:
            break
    return x, fun, cost, 0


@numba.njit(cache=True)
def square_share_kernel(d, u, v, width, nodes):  # pragma: no cover - compiled
    """Share of a unit pixel on the high side of an S-curve step, per signed distance ``d``.

    For a sharp step, the area of the unit square centred at 0 where ``x u + y v <=
    t`` (``u``, ``v`` >= 0 the normal's components) is the distribution of ``u U1 +
    v U2`` for independent uniform U1, U2 on [-1/2, 1/2]: a trapezoid, piecewise
    quadratic/linear in ``t``. The S-curve of ``width`` smooths it: the mean over the
    logistic quadrature ``nodes``.
    """
    big, small = max(u, v), min(u, v)
    half_diff, half_sum = 0.5 * (big - small), 0.5 * (big + small)
    out = np.empty(len(d))
    for i in range(len(d)):
        total = 0.0
        for q in nodes:
            value, _ = _trapezoid(d[i] + width * q, big, small, half_diff, half_sum)
            total += min(max(value, 0.0), 1.0)
        out[i] = total / len(nodes)
    return out


@numba.njit(cache=True, inline="always")
def _trapezoid(t, big, small, half_diff, half_sum):  # pragma: no cover - compiled
    """The unit square's share on the low side of the line at ``t`` (unclipped) and its density, d share / d t."""
    if small < 1e-9:
        return t / big + 0.5, 1.0 / big
    if t <= -half_diff:
        x = t + half_sum
        return (x * x / (2 * big * small), x / (big * small)) if x > 0 else (0.0, 0.0)
    if t < half_diff:
        return (t + 0.5 * big) / big, 1.0 / big
    x = -t + half_sum
    return (1.0 - x * x / (2 * big * small), x / (big * small)) if x > 0 else (1.0, 0.0)


@numba.njit(cache=True)
def square_share_slopes(d, u, v, width, nodes):  # pragma: no cover - compiled
    """:func:`square_share_kernel` and its derivatives: ``(share, d share / d d, mean of node x slope)``.

    The share's derivative in the signed distance is the trapezoid's density (the length
    of the line ``x u + y v = t`` inside the unit square), averaged over the quadrature
    nodes as the share is; the third array is the same average weighted by each node
    (a node moves ``t`` by ``width * node``), from which the derivative in the width follows.
    Zero where the share is clipped.
    """
    big, small = max(u, v), min(u, v)
    half_diff, half_sum = 0.5 * (big - small), 0.5 * (big + small)
    n = len(d)
    share, slope, node_slope = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        total, total_slope, total_node = 0.0, 0.0, 0.0
        for q in nodes:
            value, density = _trapezoid(d[i] + width * q, big, small, half_diff, half_sum)
            if value <= 0.0 or value >= 1.0:
                value, density = min(max(value, 0.0), 1.0), 0.0
            total += value
            total_slope += density
            total_node += density * q
        share[i] = total / len(nodes)
        slope[i] = total_slope / len(nodes)
        node_slope[i] = total_node / len(nodes)
    return share, slope, node_slope
