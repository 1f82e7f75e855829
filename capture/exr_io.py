"""Image files of a session: float32 OpenEXR for merged images, ``.npz`` for raw frames.

Merged (HDR) images are scan-line OpenEXR files, ZIP-compressed (lossless),
with one float32 channel per quantity, e.g. ``radiance`` (e-/s), ``variance``
((e-/s)^2) and ``mask`` (1.0 where at least one exposure measured the pixel,
0.0 where none did). Header attributes hold scalars (str, int, float); nested
metadata goes into one JSON string attribute, ``rig_meta``.

Raw frames are kept bit-exact as uint16 in a NumPy ``.npz`` archive
(zlib-compressed, lossless, readable without pickle): ``frames`` is an
``(N, rows, cols)`` uint16 array in acquisition order and ``meta`` a 0-d
unicode array holding a JSON list with one object per frame (exposure_s,
dark, ccd_temp_c, start_time, end_time, roi, camera, extra). ``.npz`` was
chosen over 16-bit PNG/TIFF because it needs no extra dependency, keeps a whole
stack with its metadata in one checksummed file and loads in one call.

All writes go through :mod:`capture.atomic`; the writers return the SHA-256 of
the file written.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from capture.atomic import atomic_path, sha256_file
from drivers.interfaces import ROI, Frame

#: Header names OpenEXR owns; user attributes may not use them.
RESERVED_ATTRIBUTES = frozenset(
    {
        "channels", "compression", "dataWindow", "displayWindow", "lineOrder",
        "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth", "type",
        "tiles", "name", "version", "chunkCount",
    }
)
META_ATTRIBUTE = "rig_meta"


@dataclass
class ExrImage:
    """A read EXR image: float32 channels by name, scalar attributes and the JSON metadata."""

    channels: dict[str, np.ndarray]
    attributes: dict[str, Any]
    meta: dict[str, Any] = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.channels[name]


def write_exr(
    path: str | os.PathLike[str],
    channels: Mapping[str, np.ndarray],
    attributes: Mapping[str, str | int | float] | None = None,
    meta: Mapping[str, Any] | None = None,
) -> str:
    """Write float32 channels (all of one 2-D shape) atomically; return the file's SHA-256.

    Args:
        path: target file (``.exr``).
        channels: channel name -> 2-D array (converted to float32).
        attributes: scalar header attributes (str, int or float).
        meta: JSON-serialisable metadata stored as the ``rig_meta`` attribute.

    Raises:
        ValueError: no channels, shapes differ, a channel is not 2-D, or an
            attribute is reserved or not a scalar.
    """
    if not channels:
        raise ValueError("an EXR image needs at least one channel")
    data: dict[str, np.ndarray] = {}
    shape = None
    for name, arr in channels.items():
        a = np.ascontiguousarray(arr, dtype=np.float32)
        if a.ndim != 2:
            raise ValueError(f"channel {name!r} must be 2-D, got shape {a.shape}")
        if shape is not None and a.shape != shape:
            raise ValueError(f"channel {name!r} has shape {a.shape}, expected {shape}")
        shape = a.shape
        data[name] = a
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (attributes or {}).items():
        if key in RESERVED_ATTRIBUTES or key == META_ATTRIBUTE:
            raise ValueError(f"EXR attribute name {key!r} is reserved")
        if isinstance(value, bool) or not isinstance(value, (str, int, float)):
            raise ValueError(f"EXR attribute {key!r} must be str, int or float, got {type(value).__name__}")
        header[key] = value
    if meta:
        header[META_ATTRIBUTE] = json.dumps(meta, sort_keys=True)
    with atomic_path(path) as tmp, OpenEXR.File(header, data) as f:
        f.write(str(tmp))
    return sha256_file(path)


def read_exr(path: str | os.PathLike[str]) -> ExrImage:
    """Read an EXR written by :func:`write_exr` (or any scan-line float EXR)."""
    with OpenEXR.File(os.fspath(path)) as f:
        header = dict(f.header())
        chans = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
    meta_text = header.pop(META_ATTRIBUTE, None)
    attrs = {k: v for k, v in header.items() if k not in RESERVED_ATTRIBUTES}
    meta = json.loads(meta_text) if isinstance(meta_text, str) else {}
    return ExrImage(chans, attrs, meta)


# --------------------------------------------------------------------------- raw frames


def _frame_meta(fr: Frame) -> dict[str, Any]:
    return {
        "exposure_s": float(fr.exposure_s),
        "dark": bool(fr.dark),
        "ccd_temp_c": float(fr.ccd_temp_c),
        "start_time": float(fr.start_time),
        "end_time": float(fr.end_time),
        "roi": asdict(fr.roi),
        "camera": fr.camera,
        "extra": fr.extra,
    }


def write_frames(path: str | os.PathLike[str], frames: Sequence[Frame]) -> str:
    """Store raw uint16 frames (one shape) and their metadata losslessly; return the SHA-256.

    Raises:
        ValueError: no frames, a frame is not uint16, or shapes differ.
    """
    if not frames:
        raise ValueError("no frames to write")
    shape = frames[0].data.shape
    for fr in frames:
        if fr.data.dtype != np.uint16:
            raise ValueError(f"raw frames must be uint16, got {fr.data.dtype}")
        if fr.data.shape != shape:
            raise ValueError(f"raw frames of one stack must share a shape: {fr.data.shape} != {shape}")
    stack = np.stack([fr.data for fr in frames])
    meta = json.dumps([_frame_meta(fr) for fr in frames], default=str)
    with atomic_path(path) as tmp, open(tmp, "xb") as f:
        np.savez_compressed(f, frames=stack, meta=np.array(meta))
        f.flush()
    return sha256_file(path)


def read_frames(path: str | os.PathLike[str]) -> list[Frame]:
    """Load the frames written by :func:`write_frames`, in acquisition order."""
    with np.load(Path(path), allow_pickle=False) as z:
        stack = z["frames"]
        meta = json.loads(str(z["meta"]))
    if len(meta) != stack.shape[0]:
        raise ValueError(f"{path}: {stack.shape[0]} frames but {len(meta)} metadata records")
    out = []
    for data, m in zip(stack, meta):
        out.append(
            Frame(
                data=np.ascontiguousarray(data),
                exposure_s=m["exposure_s"],
                dark=m["dark"],
                ccd_temp_c=m["ccd_temp_c"],
                start_time=m["start_time"],
                end_time=m["end_time"],
                roi=ROI(**m["roi"]),
                camera=m.get("camera", ""),
                extra=m.get("extra", {}),
            )
        )
    return out
