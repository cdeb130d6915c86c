"""A value against a type hint, in JSON's terms, and the hint named for an error message:
job configs and PPO settings are checked with these before any work starts."""

from __future__ import annotations

import numbers
import types
import typing
from typing import Any, Literal, Union


def fits_type(value: Any, hint: Any) -> bool:
    """True if ``value`` is of type ``hint``. A bool is not a number, an integer is a float,
    a list stands for a tuple, numpy's scalars count as the numbers they are; hints other
    than these (dicts, classes) are not checked here and pass."""
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if hint is type(None):
        return value is None
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return any(fits_type(value, arg) for arg in args)
    if origin is Literal:
        return value in args
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
        return isinstance(value, list | tuple) and all(fits_type(v, args[0]) for v in value)
    return True


def describe_type(hint: Any) -> str:
    """``int`` -> "an integer", ``float | None`` -> "a number or null", ... (JSON's words)."""
    names = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}
    if hint in names:
        return names[hint]
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (Union, types.UnionType):
        return " or ".join("null" if a is type(None) else describe_type(a) for a in args)
    if origin is Literal:
        return f"one of {list(args)}"
    if origin is tuple:
        plurals = {int: "integers", float: "numbers", bool: "true or false values"}
        return f"a list of {plurals.get(args[0], describe_type(args[0]))}"
    return str(hint)
