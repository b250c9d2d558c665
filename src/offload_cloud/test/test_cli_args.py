"""The shared argparse checkers: bounds inclusive unless opened, NaN and text refused with the option's name."""
import argparse
import math

import pytest

from offload_cloud.cli_args import bounded_float, bounded_int


def test_bounded_int_accepts_both_ends_and_refuses_outside():
    parse = bounded_int("--workers", 1, 4)
    assert parse("1") == 1 and parse("4") == 4
    for text in ("0", "5", "2.5", "two"):
        with pytest.raises(argparse.ArgumentTypeError, match="--workers"):
            parse(text)


def test_bounded_float_open_ends_and_nan():
    closed = bounded_float("--rate", 0.0, 1.0)
    assert closed("0") == 0.0 and closed("1") == 1.0
    opened = bounded_float("--rate", 0.0, 1.0, low_open=True, high_open=True)
    assert opened("0.5") == 0.5
    for text in ("0", "1", "nan", "inf", "x"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"--rate must be (in \(0, 1\)|a number)"):
            opened(text)
    assert bounded_float("--s", 0.0)("1e300") == 1e300
    with pytest.raises(argparse.ArgumentTypeError):
        bounded_float("--s", 0.0)("nan")
    assert math.isinf(bounded_float("--s", 0.0)("inf"))
