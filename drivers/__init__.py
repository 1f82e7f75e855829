"""Device interfaces, byte protocols and real drivers of the capture rig."""

from drivers.errors import (
    DeviceConnectionError,
    DeviceError,
    DeviceTimeout,
    LimitError,
    ParameterError,
    ProtocolError,
    StateError,
)
from drivers.interfaces import (
    ROI,
    AngleRange,
    Camera,
    CoolerStatus,
    FilterChanger,
    Frame,
    RotationStage,
    SensorInfo,
    ShutterMode,
)

__all__ = [
    "ROI", "AngleRange", "Camera", "CoolerStatus", "DeviceConnectionError", "DeviceError",
    "DeviceTimeout", "FilterChanger", "Frame", "LimitError", "ParameterError", "ProtocolError",
    "RotationStage", "SensorInfo", "ShutterMode", "StateError",
]
