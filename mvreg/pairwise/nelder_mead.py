"""Several Nelder-Mead minimisations run together, their function values asked for at once.

Takes simplices and a function of many points at a time; returns (x, value) per simplex.
Pure function of the arrays; deterministic.

Why: the sensor search of :mod:`mvreg.pairwise.viewpoint` refines four starts, each by
some hundred evaluations of a function whose cost is mostly numpy's per-call overhead
on small arrays. Run one after the other (``scipy.optimize.minimize``), that is four
hundred calls; run together, a hundred calls of four points each (200 scans of 400
points: the search took 0.27 s a scan).

How: :func:`nelder_mead` is SciPy 1.17's ``_minimize_neldermead`` without bounds or
adaptive parameters, step for step (the same arithmetic, the same sorts, the same stop
on ``xatol``, ``fatol`` and ``maxfev``, including a shrink cut short by ``maxfev``),
written as a generator that yields the points it needs and receives their values;
``tests/test_viewpoint.py`` compares it with SciPy bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Sequence

import numpy as np

RHO, CHI, PSI, SIGMA = 1, 2, 0.5, 0.5  # SciPy's non-adaptive coefficients


class _Exhausted(Exception):
    """``maxfev`` evaluations were made and another was asked for."""


def _ask(x: np.ndarray, calls: list[int], maxfev: int):
    if calls[0] >= maxfev:
        raise _Exhausted
    calls[0] += 1
    return (yield np.copy(x))


def _sorted(sim, fsim):
    ind = np.argsort(fsim)
    return np.take(sim, ind, 0), np.take(fsim, ind, 0)


def nelder_mead(
    simplex: np.ndarray, xatol: float, fatol: float, maxfev: int
) -> Generator[np.ndarray, float, tuple[np.ndarray, float]]:
    """Nelder-Mead from ``simplex`` (N + 1, N): yields points, is sent their values,
    returns (x, value) as ``scipy.optimize.minimize(..., method="Nelder-Mead",
    options={"initial_simplex": simplex, "xatol", "fatol", "maxfev"})`` gives them."""
    sim = np.asarray(simplex, dtype=np.float64).copy()
    n = sim.shape[1]
    fsim = np.full((n + 1,), np.inf, dtype=float)
    calls = [0]
    try:
        for k in range(n + 1):
            fsim[k] = yield from _ask(sim[k], calls, maxfev)
    except _Exhausted:
        pass
    sim, fsim = _sorted(sim, fsim)
    sim, fsim = _sorted(sim, fsim)  # SciPy sorts twice here; ties may be reordered
    while calls[0] < maxfev:
        try:
            with np.errstate(invalid="ignore"):  # inf - inf: NaN, not within fatol, as in SciPy
                done = (
                    np.max(np.ravel(np.abs(sim[1:] - sim[0]))) <= xatol
                    and np.max(np.abs(fsim[0] - fsim[1:])) <= fatol
                )
            if done:
                break
            yield from _step(sim, fsim, n, calls, maxfev)
        except _Exhausted:
            pass
        sim, fsim = _sorted(sim, fsim)
    return sim[0], float(np.min(fsim))


def _step(sim, fsim, n, calls, maxfev):
    """One iteration (reflect, expand, contract or shrink), in place."""
    xbar = np.add.reduce(sim[:-1], 0) / n
    xr = (1 + RHO) * xbar - RHO * sim[-1]
    fxr = yield from _ask(xr, calls, maxfev)
    if fxr < fsim[0]:
        xe = (1 + RHO * CHI) * xbar - RHO * CHI * sim[-1]
        fxe = yield from _ask(xe, calls, maxfev)
        sim[-1], fsim[-1] = (xe, fxe) if fxe < fxr else (xr, fxr)
        return
    if fxr < fsim[-2]:
        sim[-1], fsim[-1] = xr, fxr
        return
    if fxr < fsim[-1]:  # contraction outside
        xc = (1 + PSI * RHO) * xbar - PSI * RHO * sim[-1]
        fxc = yield from _ask(xc, calls, maxfev)
        if fxc <= fxr:
            sim[-1], fsim[-1] = xc, fxc
            return
    else:  # inside
        xcc = (1 - PSI) * xbar + PSI * sim[-1]
        fxcc = yield from _ask(xcc, calls, maxfev)
        if fxcc < fsim[-1]:
            sim[-1], fsim[-1] = xcc, fxcc
            return
    for j in range(1, n + 1):  # shrink towards the best
        sim[j] = sim[0] + SIGMA * (sim[j] - sim[0])
        fsim[j] = yield from _ask(sim[j], calls, maxfev)


def minimize_together(
    values: Callable[[list[tuple[int, np.ndarray]]], Sequence[float]],
    simplices: Sequence[np.ndarray],
    xatol: float,
    fatol: float,
    maxfev: int,
) -> list[tuple[np.ndarray, float]]:
    """(x, value) of :func:`nelder_mead` from each of ``simplices``, all advanced together:
    ``values`` gets the [(simplex index, point), ...] every unfinished run asks for next
    and returns their values in that order."""
    runs = [nelder_mead(s, xatol, fatol, maxfev) for s in simplices]
    out: list = [None] * len(runs)
    asked = {}
    for k, run in enumerate(runs):
        try:
            asked[k] = next(run)
        except StopIteration as stop:  # maxfev 0
            out[k] = stop.value
    while asked:
        items = list(asked.items())
        for (k, _), v in zip(items, values(items), strict=True):
            try:
                asked[k] = runs[k].send(float(v))
            except StopIteration as stop:
                out[k] = stop.value
                del asked[k]
    return out
