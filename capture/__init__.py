"""Sequencer, HDR merging and the session directory (sees device interfaces only)."""
