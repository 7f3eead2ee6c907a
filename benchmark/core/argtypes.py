"""Range-checked numbers for the command line: argparse ``type=`` functions.

Every numeric option of every command is parsed by one of these, so a value out of range is an
argparse usage error (exit 2, ``usage: ...`` and one line naming the option, the value and the
allowed range) before any work starts. Nothing falls back to a default: an option left out is
``None`` (or its stated default), and 0 or a negative number is either allowed by the range or
refused, never read as "not given".

    p.add_argument("--steps", type=positive_int, default=None)
    p.add_argument("--fps", type=fps, default=10.0)

argparse prints ``argument --steps: 0 is out of range (allowed: an integer >= 1)``.
"""

from __future__ import annotations

import argparse
import math

__all__ = ["Number", "positive_int", "non_negative_int", "positive_float", "non_negative_float", "fraction",
           "fps", "seed", "jobs", "points", "FPS_MIN", "FPS_MAX", "MAX_POINTS", "MAX_JOBS", "MAX_SEED"]

FPS_MIN, FPS_MAX = 1.0, 1000.0  # frames per second: a capture, an observation rate or a resampling rate
MAX_POINTS = 1_000_000  # points per frame: a scan this harness can hold in memory for a whole window
MAX_JOBS = 1024  # worker processes
MAX_SEED = 2**32 - 1  # numpy's legacy seeding takes 32 bits


def _fmt(x: float) -> str:
    return format(x, "g") if isinstance(x, float) else str(x)


class Number:
    """``type=`` callable: parse an int (``kind=int``) or a finite float (``kind=float``) and check
    ``lo <= x <= hi`` (``lo < x`` with ``lo_open``, ``x < hi`` with ``hi_open``); either bound may be
    None. Raises :class:`argparse.ArgumentTypeError`, which argparse prefixes with the option."""

    def __init__(self, kind: type, lo=None, hi=None, *, lo_open: bool = False, hi_open: bool = False, unit: str = ""):
        if kind not in (int, float):
            raise TypeError("kind must be int or float")
        self.kind, self.lo, self.hi, self.lo_open, self.hi_open, self.unit = kind, lo, hi, lo_open, hi_open, unit
        # argparse names the type in some messages (and in --help when asked to): a readable name
        self.__name__ = self.describe()

    def describe(self) -> str:
        """The allowed values in words: ``an integer >= 1``, ``a number in [0, 1)``, ``a number in 1..1000``."""
        noun = "an integer" if self.kind is int else "a number"
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            if not (self.lo_open or self.hi_open):
                text = f"{noun} in {_fmt(lo)}..{_fmt(hi)}"
            else:
                text = f"{noun} in {'(' if self.lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if self.hi_open else ']'}"
        elif lo is not None:
            text = f"{noun} {'>' if self.lo_open else '>='} {_fmt(lo)}"
        elif hi is not None:
            text = f"{noun} {'<' if self.hi_open else '<='} {_fmt(hi)}"
        else:
            text = noun
        return text + (f" {self.unit}" if self.unit else "")

    def __repr__(self) -> str:
        return f"Number({self.describe()})"

    def __call__(self, text):
        value = self._parse(text)
        lo, hi = self.lo, self.hi
        below = lo is not None and (value <= lo if self.lo_open else value < lo)
        above = hi is not None and (value >= hi if self.hi_open else value > hi)
        if below or above:
            raise argparse.ArgumentTypeError(f"{text} is out of range (allowed: {self.describe()})")
        return value

    def _parse(self, text):
        s = str(text).strip()
        if self.kind is int:
            try:
                return int(s, 10)
            except ValueError:
                pass
            try:  # "1e3" or "200.0": accepted when it is a whole number
                f = float(s)
            except ValueError:
                f = None
            if f is not None and math.isfinite(f) and f.is_integer():
                return int(f)
            raise argparse.ArgumentTypeError(f"{text!r} is not {self.describe()}")
        try:
            value = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {self.describe()}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text} is not finite (allowed: {self.describe()})")
        return value


positive_int = Number(int, 1)
non_negative_int = Number(int, 0)
positive_float = Number(float, 0.0, lo_open=True)
non_negative_float = Number(float, 0.0)
fraction = Number(float, 0.0, 1.0, hi_open=True)  # a share in [0, 1)
fps = Number(float, FPS_MIN, FPS_MAX, unit="frames per second")
seed = Number(int, 0, MAX_SEED)
jobs = Number(int, 1, MAX_JOBS)
points = Number(int, 1, MAX_POINTS, unit="points per frame")



class Once(argparse.Action):
    """``action=Once``: an option that may be given at most once. argparse's default keeps the
    last of repeated values without a word (``--weights A --weights B`` would silently use B)."""

    def __call__(self, parser, namespace, values, option_string=None):
        seen = f"_given_{self.dest}"
        if getattr(namespace, seen, False):
            parser.error(f"argument {option_string}: given twice ({getattr(namespace, self.dest)!r} and {values!r}); "
                         "give it once")
        setattr(namespace, seen, True)
        setattr(namespace, self.dest, values)
