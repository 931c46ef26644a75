"""Vortex-shedding figures from drag/lift histories: Strouhal number, force extrema, onset.

All functions take the per-step force history of :class:`~diffgns.mesh.cfd.CaseResult`
(``times`` (S,) s, ``cd``/``cl`` (S,) dimensionless).
"""
from __future__ import annotations

import numpy as np


def _upward_crossings(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Times (linearly interpolated) at which ``x`` crosses zero going up."""
    i = np.nonzero((x[:-1] < 0) & (x[1:] >= 0))[0]
    return t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])


def lift_periods(times: np.ndarray, cl: np.ndarray, t_from: float = 0.0) -> np.ndarray:
    """Start times of the lift periods after ``t_from`` (upward crossings of cL - mean cL)."""
    m = times >= t_from
    t, x = times[m], cl[m]
    return _upward_crossings(t, x - 0.5 * (x.max() + x.min())) if len(t) > 2 else np.zeros(0)


def period_amplitudes(times: np.ndarray, cl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(start times, peak-to-peak cL amplitude) of every complete lift period."""
    starts = _upward_crossings(times, cl - np.median(cl))
    amps = np.array([np.ptp(cl[(times >= a) & (times < b)]) for a, b in zip(starts, starts[1:])])
    return starts[:-1], amps


def shedding_metrics(times: np.ndarray, cd: np.ndarray, cl: np.ndarray, t_from: float,
                     diameter: float, u_bar: float) -> dict:
    """Periodic-flow figures over ``times >= t_from``, as in Schäfer & Turek (1996) 2D-2.

    Only whole lift periods are used. Returns ``strouhal`` (f D / Ubar), ``frequency`` (Hz),
    ``n_periods``, ``cd_max``/``cd_min``/``cd_mean``, ``cl_max``/``cl_min``, and
    ``cl_amplitude_drift`` (relative change of the peak-to-peak cL from the first to the last
    period in the window; small means periodic). Values are NaN without two whole periods.
    """
    starts = lift_periods(times, cl, t_from)
    out = dict(t_from=float(t_from), n_periods=max(len(starts) - 1, 0))
    keys = ["strouhal", "frequency", "cd_max", "cd_min", "cd_mean", "cl_max", "cl_min",
            "cl_amplitude_drift"]
    if len(starts) < 3:
        return {**out, **{k: float("nan") for k in keys}}
    f = (len(starts) - 1) / (starts[-1] - starts[0])
    w = (times >= starts[0]) & (times < starts[-1])
    amps = [np.ptp(cl[(times >= a) & (times < b)]) for a, b in zip(starts, starts[1:])]
    return {**out, "strouhal": float(f * diameter / u_bar), "frequency": float(f),
            "cd_max": float(cd[w].max()), "cd_min": float(cd[w].min()),
            "cd_mean": float(cd[w].mean()), "cl_max": float(cl[w].max()),
            "cl_min": float(cl[w].min()),
            "cl_amplitude_drift": float(abs(amps[-1] - amps[0]) / amps[-1])}


def shedding_onset(times: np.ndarray, cl: np.ndarray, tol: float = 0.02) -> float:
    """First time from which every lift period's peak-to-peak amplitude stays within ``tol``
    (relative) of the last complete period's, i.e. when shedding is established.

    Returns NaN if there are fewer than three complete periods (no shedding yet).
    """
    starts, amps = period_amplitudes(times, cl)
    if len(amps) < 3 or amps[-1] <= 0:
        return float("nan")
    ok = np.abs(amps - amps[-1]) <= tol * amps[-1]
    bad = np.nonzero(~ok)[0]
    first_ok = bad[-1] + 1 if len(bad) else 0
    return float(starts[first_ok]) if first_ok < len(amps) else float("nan")
