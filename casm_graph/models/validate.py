"""Checks of a model.json document's fields: each failure is one :class:`LogError` line naming the file and the
field (the model itself and each action-model part read their own fields through :class:`Where`)."""
from __future__ import annotations

import math

import numpy as np

from casm_graph.io.log import LogError

MAX_NESTING = 20            # effects and fit entries deeper than this are not a model's
MAX_POLY = 7                # reading_poly: degree 6 at most (calibrate's --sensor-degree)
SIGMA_SPAN = (1e-12, 1e9)   # noise levels: smaller is no noise at float precision, larger no sensor
COEFFICIENT_SPAN = (0.0, 1e12)     # sensor polynomial coefficients: beyond, the curve overflows


def no_constant(name: str):
    """``json.loads``'s hook for NaN and Infinity, which strict JSON (and a model) does not hold."""
    raise ValueError(f"{name} is not valid JSON (write null for an unknown value)")


def one_line(s: str) -> str:
    """``s`` on one line, cut at 120 characters: a message quotes what it got without flooding the terminal."""
    s = " ".join(s.split())
    return s if len(s) <= 120 else s[:120] + "..."


def kind_of(x) -> str:
    """What JSON value ``x`` is, in words."""
    return {dict: "an object", list: "a list", str: "a string", bool: "true/false",
            type(None): "null"}.get(type(x), "a number")


def expected(x, what: str) -> str:
    """The message for a field that holds ``x`` where ``what`` belongs."""
    if x is None:
        return f"is missing or null (expected {what})"
    return f"must be {what} (got {kind_of(x)})"


class Where:
    """The checks of one document's fields, each failing with one line that names the file (``source``) and field."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, where: str, what: str):
        raise LogError(f"{self.source}: {where} {what}")

    def obj(self, x, where: str) -> dict:
        if not isinstance(x, dict):
            self.fail(where, expected(x, "a JSON object"))
        return x

    def num(self, x, where: str, positive: bool = False, nonneg: bool = False,
            span: tuple[float, float] | None = None) -> float:
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            self.fail(where, expected(x, "a number"))
        try:
            v = float(x)
        except OverflowError:
            v = math.inf
        if not math.isfinite(v):
            self.fail(where, "must be a finite number")
        if positive and not v > 0:
            self.fail(where, f"must be positive (got {v:g})")
        if nonneg and v < 0:
            self.fail(where, f"must not be negative (got {v:g})")
        if span is not None and v != 0 and not span[0] <= abs(v) <= span[1]:
            self.fail(where, f"is {v:g}, outside what its units allow ({span[0]:g} to {span[1]:g} in size)")
        return v

    def vec(self, x, where: str, n: int | None = None, nullable: bool = False, nonneg: bool = False,
            positive: bool = False, max_len: int | None = None, span: tuple[float, float] | None = None) -> np.ndarray:
        """A list of finite numbers (null read as NaN where ``nullable``) of length ``n`` when given."""
        if not isinstance(x, list):
            self.fail(where, expected(x, "a list of numbers"))
        if n is not None and len(x) != n:
            self.fail(where, f"must hold {n} numbers (got {len(x)})")
        if not x or (max_len is not None and len(x) > max_len):
            self.fail(where, f"must hold 1 to {max_len or 'any'} numbers (got {len(x)})")
        return np.array([np.nan if (v is None and nullable) else
                         self.num(v, f"{where}[{i}]", positive=positive, nonneg=nonneg, span=span)
                         for i, v in enumerate(x)], float)

    def plain(self, x, where: str, depth: int = 0) -> None:
        """Free-form content (effects, fit): finite numbers, strings, true/false, null, lists, objects."""
        if depth > MAX_NESTING:
            self.fail(where, f"is nested more than {MAX_NESTING} levels deep")
        if isinstance(x, dict):
            for k, v in x.items():
                self.plain(v, f"{where}.{k}", depth + 1)
        elif isinstance(x, list):
            for i, v in enumerate(x):
                self.plain(v, f"{where}[{i}]", depth + 1)
        elif isinstance(x, (int, float)) and not isinstance(x, bool):
            self.num(x, where)
