"""Errors of the capture layer."""


class CaptureError(Exception):
    """Base of capture errors; the message is one line for the operator."""


class SessionError(CaptureError, ValueError):
    """Raised when a session directory is missing, corrupt, unwritable, full, or
    does not match the request (resuming with a different plan)."""


class PlanError(CaptureError, ValueError):
    """Raised before any hardware moves when a plan cannot be made (angle count,
    ranges, unknown filter, angle outside the stage's allowed range)."""
