"""Beam calibration and dark/bias frames."""
