"""Shared fixtures. Device tests run against the byte-level twins."""

import os

# Mitsuba's CPU backend: prefer libLLVM 19 (15/16 abort at the first render).
os.environ.setdefault("MPLBACKEND", "Agg")
