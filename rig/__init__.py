"""rig: drive the goniometric capture rig and estimate scattering parameters."""

__version__ = "0.1.0"
