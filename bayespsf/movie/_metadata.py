"""Pixel size (nm) and exposure (s) from a movie's OME or ImageJ metadata, where present."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

# nanometres per unit of length, seconds per unit of time; "u" stands for the micro sign
_NM = {
    "m": 1e9,
    "dm": 1e8,
    "cm": 1e7,
    "mm": 1e6,
    "um": 1e3,
    "micron": 1e3,
    "microns": 1e3,
    "micrometer": 1e3,
    "micrometre": 1e3,
    "nm": 1.0,
    "pm": 1e-3,
    "a": 0.1,
    "angstrom": 0.1,
    "å": 0.1,
}
_SECONDS = {
    "s": 1.0,
    "sec": 1.0,
    "second": 1.0,
    "seconds": 1.0,
    "ms": 1e-3,
    "msec": 1e-3,
    "us": 1e-6,
    "ns": 1e-9,
    "min": 60.0,
    "h": 3600.0,
}


@dataclass
class FileMetadata:
    """What a file's metadata say: pixel size in nm, exposure in s (each None where absent),
    where each came from (``"OME"``, ``"ImageJ"`` or None) and the channel names, if any."""

    pixel_size: float | None = None
    exposure: float | None = None
    metadata: dict = field(default_factory=lambda: {"pixel_size": None, "exposure": None})
    channel_names: list[str] = field(default_factory=list)


def _unit(text: str) -> str:
    """A unit's name in lower case with the micro sign (either code point, or ImageJ's
    escaped ``\\u00B5``) written ``u``."""
    return text.strip().replace("\\u00B5", "u").replace("µ", "u").replace("μ", "u").lower()


def _scaled(value, unit: str, table: dict[str, float]) -> float | None:
    """``value`` in ``unit`` converted by ``table``; None if either is missing or not usable."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    factor = table.get(_unit(unit))
    if factor is None or not number > 0 or number == float("inf"):
        return None
    return number * factor


def from_ome(xml: str, channel: int | None) -> FileMetadata:
    """OME-XML: ``PhysicalSizeX`` (unit ``PhysicalSizeXUnit``, default µm) for the pixel size;
    the ``ExposureTime`` of the first plane of the channel (unit ``ExposureTimeUnit``) for the
    exposure, else ``TimeIncrement`` (the frame interval, an upper bound on the exposure)."""
    found = FileMetadata()
    try:
        pixels = ET.fromstring(xml).find("{*}Image/{*}Pixels")
    except ET.ParseError:
        return found
    if pixels is None:
        return found
    found.channel_names = [c.get("Name", "") for c in pixels.findall("{*}Channel")]
    found.pixel_size = _scaled(
        pixels.get("PhysicalSizeX"), pixels.get("PhysicalSizeXUnit", "µm"), _NM
    )
    for plane in pixels.findall("{*}Plane"):
        if channel is None or plane.get("TheC", "0") == str(channel):
            unit = plane.get("ExposureTimeUnit", "s")
            found.exposure = _scaled(plane.get("ExposureTime"), unit, _SECONDS)
            found.metadata["exposure_field"] = "ExposureTime"
            break
    if found.exposure is None:
        unit = pixels.get("TimeIncrementUnit", "s")
        found.exposure = _scaled(pixels.get("TimeIncrement"), unit, _SECONDS)
        found.metadata["exposure_field"] = "TimeIncrement"
    _sources(found, "OME")
    return found


def from_imagej(tif) -> FileMetadata:
    """ImageJ: the pixel size from the XResolution tag (pixels per ``unit``; ImageJ's
    ``spacing`` is the Z step, not the pixel size) and the frame interval ``finterval`` (in
    ``tunit``, default seconds) for the exposure (an upper bound on it)."""
    found = FileMetadata()
    info = tif.imagej_metadata or {}
    tag = tif.pages[0].tags.get("XResolution")
    if tag is not None and "unit" in info:
        numerator, denominator = tag.value
        if numerator > 0:
            found.pixel_size = _scaled(denominator / numerator, str(info["unit"]), _NM)
    found.exposure = _scaled(info.get("finterval"), str(info.get("tunit", "s")), _SECONDS)
    if found.exposure is not None:
        found.metadata["exposure_field"] = "finterval"
    _sources(found, "ImageJ")
    return found


def _sources(found: FileMetadata, kind: str) -> None:
    found.metadata["pixel_size"] = kind if found.pixel_size is not None else None
    found.metadata["exposure"] = kind if found.exposure is not None else None
    if found.exposure is None:
        found.metadata.pop("exposure_field", None)
