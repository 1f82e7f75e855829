"""Errors of the estimation layer."""


class EstimateError(Exception):
    """Base of estimation errors; the message is one line for the user."""


class ModelParameterError(EstimateError, ValueError):
    """Raised for an invalid physical parameter: negative or NaN coefficients,
    thickness <= 0, refractive index < 1, unknown phase model or extension name.
    The message names the parameter."""


class DataError(EstimateError, ValueError):
    """Raised for unusable input data: a phase-function table with non-positive or
    NaN values or bad angles, a session with missing stacks, NaN radiance."""
