"""File names derived from labels (``x=30``, ``kp_steer=0.8,kp_speed=18``) that are safe everywhere."""

from __future__ import annotations

import re


def safe_name(text: str) -> str:
    """Letters, digits, ``.``, ``-``, ``_`` and ``=`` kept; anything else becomes ``_``."""
    return re.sub(r"[^A-Za-z0-9._=-]+", "_", text).strip("._") or "figure"
