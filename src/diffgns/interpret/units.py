"""Dimensional analysis of symbolic expressions.

Units are exponent vectors over the SI base units (kg, m, s), written as strings like
``"kg m s^-2"`` or ``"N"``. Fitted real constants (sympy ``Float``) are *wildcards*: they may
carry whatever unit makes the expression consistent (``100.0 * (d - r_i)`` is a force when the
constant is in N/m). Exact numbers (``Integer``, ``Rational``, such as the ``-1`` of a
subtraction) are dimensionless.

Rules (``check(expr, units, target)``):

* ``a + b``, ``min(a, b)``, ``max(a, b)``: every operand with a definite unit must have the
  same unit; wildcards adapt.
* ``a * b``: units add; a wildcard factor makes the product a wildcard.
* ``a ** p``: ``p`` must be a number; a dimensioned base needs a half-integer ``p`` (within
  1e-3) and gets its unit times ``p``. A symbolic exponent needs both base and exponent
  dimensionless.
* ``exp``, ``log`` and other transcendental functions need a dimensionless (or wildcard)
  argument and give a dimensionless result; ``abs`` keeps the unit.
* The expression's unit must equal ``target`` (or be a wildcard); ``target=None`` checks only
  internal consistency.
"""
from __future__ import annotations

import numpy as np

from diffgns._extras import require

sympy = require("sympy", "symbolic")

BASE = ("kg", "m", "s")
_NAMED = {"N": (1, 1, -2), "J": (1, 2, -2), "1": (0, 0, 0), "": (0, 0, 0)}
WILD = None  # a wildcard unit


class DimensionError(ValueError):
    """An expression mixes incompatible units."""


def parse_unit(text: str) -> np.ndarray:
    """``"kg m s^-2"``, ``"m/s"``, ``"N"`` -> exponent vector (3,) over (kg, m, s)."""
    out = np.zeros(3)
    num, _, den = text.replace("*", " ").partition("/")
    for part, sign in ((num, 1.0), (den, -1.0)):
        for tok in part.split():
            name, _, power = tok.partition("^")
            p = float(power) if power else 1.0
            if name in BASE:
                out[BASE.index(name)] += sign * p
            elif name in _NAMED:
                out += sign * p * np.asarray(_NAMED[name], float)
            else:
                raise ValueError(f"unknown unit {name!r} in {text!r}; use {BASE} or N, J")
    return out


def format_unit(u) -> str:
    if u is WILD:
        return "any"
    parts = [f"{b}^{p:g}" if p != 1 else b for b, p in zip(BASE, u) if abs(p) > 1e-9]
    return " ".join(parts) or "1"


def _same(a, b) -> bool:
    return np.allclose(a, b, atol=1e-6)


def _combine_equal(units: list, what: str, where) -> object:
    fixed = [u for u in units if u is not WILD]
    for u in fixed[1:]:
        if not _same(u, fixed[0]):
            raise DimensionError(f"{what} of {format_unit(fixed[0])} and {format_unit(u)} "
                                 f"in {where}")
    return fixed[0] if fixed else WILD


def _dimensionless(u) -> bool:
    return u is WILD or np.allclose(u, 0)


def apply(op: str, args: list, where="", power: float | None = None):
    """Unit of ``op`` applied to operands of units ``args`` (vectors or :data:`WILD`).

    ``op``: "add" (also sub, min, max), "mul", "div", "inv", "pow" (``power`` is the numeric
    exponent, or None for a symbolic exponent given as ``args[1]``), "abs", or "func" (exp,
    log and other transcendental functions). Raises :class:`DimensionError`.
    """
    if op == "add":
        return _combine_equal(args, "sum", where)
    if op in ("mul", "div"):
        if any(a is WILD for a in args):
            return WILD
        return args[0] + args[1] if op == "mul" else args[0] - args[1]
    if op == "inv":
        return WILD if args[0] is WILD else -args[0]
    if op == "abs":
        return args[0]
    if op == "pow":
        base = args[0]
        if power is None:
            for u, what in ((base, "base"), (args[1], "exponent")):
                if not _dimensionless(u):
                    raise DimensionError(f"{what} of a symbolic power has unit "
                                         f"{format_unit(u)} in {where}")
            return WILD if base is WILD else np.zeros(3)
        if base is WILD or np.allclose(base, 0):
            return base
        if abs(2 * power - round(2 * power)) > 2e-3:
            raise DimensionError(f"non-integer power {power:g} of {format_unit(base)} in "
                                 f"{where}")
        return base * round(2 * power) / 2
    if op == "func":
        for u in args:
            if not _dimensionless(u):
                raise DimensionError(f"function of {format_unit(u)} in {where}")
        return np.zeros(3)
    raise ValueError(f"unknown operation {op!r}")


def unit_of(expr: sympy.Expr, units: dict[str, np.ndarray]):
    """Unit of ``expr`` (exponent vector or :data:`WILD`); raises :class:`DimensionError`."""
    if expr.is_Symbol:
        if expr.name not in units:
            raise KeyError(f"no unit declared for variable {expr.name!r}")
        return np.asarray(units[expr.name], float)
    if isinstance(expr, sympy.Float) or expr in (sympy.pi, sympy.E):
        return WILD
    if expr.is_Number:
        return np.zeros(3)
    if expr.is_Pow:
        base = unit_of(expr.base, units)
        if expr.exp.is_Number:
            return apply("pow", [base], expr, power=float(expr.exp))
        return apply("pow", [base, unit_of(expr.exp, units)], expr)
    args = [unit_of(a, units) for a in expr.args]
    if expr.is_Add or isinstance(expr, (sympy.Min, sympy.Max)):
        return apply("add", args, expr)
    if expr.is_Mul:
        out = args[0]
        for a in args[1:]:
            out = apply("mul", [out, a], expr)
        return out
    if isinstance(expr, sympy.Abs):
        return args[0]
    if isinstance(expr, sympy.Function):
        return apply("func", args, expr)
    raise DimensionError(f"cannot analyse {type(expr).__name__} in {expr}")


def parse_units(units: dict) -> dict[str, np.ndarray]:
    """Name -> unit string or vector, as exponent vectors."""
    return {k: parse_unit(v) if isinstance(v, str) else np.asarray(v, float)
            for k, v in units.items()}


def verdict(unit, target: str | None) -> tuple[bool, str]:
    """(consistent, note) for an expression of ``unit`` that should have ``target``."""
    if target is not None and unit is not WILD and not _same(unit, parse_unit(target)):
        return False, f"unit {format_unit(unit)}, expected {target}"
    return True, f"unit {format_unit(unit)}"


def check(expr: sympy.Expr, units: dict[str, str | np.ndarray], target: str | None = None):
    """(consistent, reason): whether ``expr`` is dimensionally consistent (see module doc)."""
    try:
        u = unit_of(expr, parse_units(units))
    except DimensionError as err:
        return False, str(err)
    return verdict(u, target)
