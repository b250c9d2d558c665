"""argparse value checkers shared by the workspace's command-line tools (cloud server, WAN emulator, the
learner's demo and benchmarks): one wording of a bound, and NaN never slips through."""
import argparse
import math


def bounded_int(name: str, low: int, high: int):
    """An integer within [low, high]."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{name} must be in {low}..{high}, got {value}")
        return value
    return parse


def bounded_float(name: str, low: float = -math.inf, high: float = math.inf, low_open: bool = False,
                  high_open: bool = False):
    """A float within [low, high]; either end open on request. NaN fails every comparison, so it is refused."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        above_low = low < value if low_open else low <= value
        below_high = value < high if high_open else value <= high
        if not (above_low and below_high):
            bounds = f"{'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
            raise argparse.ArgumentTypeError(f"{name} must be in {bounds}, got {text!r}")
        return value
    return parse
