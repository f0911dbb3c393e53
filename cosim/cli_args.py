"""Argument types and option groups the `cosim` command's subcommands share (``cosim.cli``)."""

from __future__ import annotations

import argparse


def add_ray_options(parser: argparse.ArgumentParser) -> None:
    """``--workers`` and ``--address``: where fanned-out runs go (``cosim.scale.pool``)."""
    parser.add_argument(
        "--workers", type=positive_int, help="Ray worker processes (default: the cores, or the cluster's CPUs)"
    )
    parser.add_argument("--address", help="a Ray cluster's address (e.g. 10.0.0.5:6379); default: a local Ray")


def positive_ints(text: str) -> list[int]:
    """A comma-separated list of positive integers ("1,2,4")."""
    return [positive_int(word) for word in text.split(",")]


def words(text: str) -> list[str]:
    """A comma-separated list of words ("serial,coloured")."""
    return [w.strip() for w in text.split(",") if w.strip()]


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return value
