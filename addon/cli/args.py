"""Argument types the commands share: numbers as argparse should take them (finite, whole where a count or size)."""

from __future__ import annotations

import argparse
import math


def finite_float(text: str) -> float:
    """A finite number: ``nan`` and ``inf`` parse as floats but mean nothing as a setting."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


finite_float.__name__ = "number"  # argparse names the type in its messages
