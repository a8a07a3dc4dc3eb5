"""Argument types shared by the benchmarks' command lines."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

__all__ = ["names_from"]


def names_from(text: str, known: Sequence[str], what: str) -> list[str]:
    """Comma-separated names out of ``known`` (or ``all`` of them), refused by name if unknown."""
    names = list(known) if text == "all" else [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"unknown {what}(s) {unknown}; choose from {', '.join(known)}")
    return names
