"""Pixel size (nm) and exposure (s) from a movie's OME or ImageJ metadata, where present."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

from bayespsf.errors import BayespsfInputError

# a pixel's side at the sample: camera pixels of 2-30 µm behind 10x-250x objectives
PIXEL_SIZE_RANGE = (1.0, 10_000.0)  # nm
# nanometres per unit of length (OME's UnitsLength, ImageJ's names), seconds per unit of time;
# "u" stands for the micro sign
_NM = {
    "km": 1e12,
    "hm": 1e11,
    "dam": 1e10,
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
    "fm": 1e-6,
    "a": 0.1,
    "angstrom": 0.1,
    "å": 0.1,
    "in": 2.54e7,
    "inch": 2.54e7,
    "ft": 3.048e8,
    "yd": 9.144e8,
    "thou": 2.54e4,
    "li": 2.54e7 / 12,
    "pt": 2.54e7 / 72,
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
    size, unit = pixels.get("PhysicalSizeX"), pixels.get("PhysicalSizeXUnit", "µm")
    found.pixel_size = _scaled(size, unit, _NM)
    _field(found, size, f"PhysicalSizeX = {size} {unit}", f"PhysicalSizeXUnit {unit!r}")
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
            unit = str(info["unit"])
            found.pixel_size = _scaled(denominator / numerator, unit, _NM)
            text = f"XResolution {numerator / denominator:g} pixels per {unit}"
            _field(found, numerator, text, f"unit {unit!r}")
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


def _field(found: FileMetadata, value, text: str, unit: str) -> None:
    """Record which field gave the pixel size, or why a field that is there gave none."""
    if found.pixel_size is not None:
        found.metadata["pixel_size_field"] = text
    elif value is not None:
        found.metadata["pixel_size_note"] = (
            f"{text}: not read as a pixel size ({unit} is not a known unit of length, or "
            "the value is not a positive number)"
        )


def check_pixel_size(pixel_size, source: str = "given") -> float:
    """``pixel_size`` (nm) if it is a plausible pixel size at the sample, else an error.

    Parameters
    ----------
    pixel_size : float
        The pixel side at the sample, nm.
    source : str
        Where it came from, for the message (e.g. the movie's metadata field).

    Returns
    -------
    float
        ``pixel_size`` as a float.

    Raises
    ------
    BayespsfInputError
        Outside ``PIXEL_SIZE_RANGE`` (1 nm to 10 µm): a unit mistaken (µm or mm for nm, or
        the camera's own pixel pitch instead of its size at the sample), naming the fixes.
    """
    low, high = PIXEL_SIZE_RANGE
    value = float(pixel_size)
    if not low <= value <= high:
        raise BayespsfInputError(
            f"pixel_size {value:g} nm ({source}) is not a pixel size at the sample, which lies "
            f"between {low:g} nm and {high / 1000:g} µm (a camera's pixel pitch over the "
            "objective's magnification, typically 50-250 nm): is its unit right? Give the "
            "pixel size at the sample in nm: [geometry] pixel_size in the camera file, "
            "--pixel-size, or pixel_size="
        )
    return value


def resolve_pixel_size(pixel_size, camera, movie) -> float:
    """The pixel size (nm) of a movie's analysis: ``pixel_size`` if given, else the camera
    Model's, else the movie's metadata; checked (``check_pixel_size``), naming its source."""
    from bayespsf import psf

    source = "pixel_size="
    if pixel_size is None:
        pixel_size, source = getattr(camera, "pixel_size", None), "the Model's pixel_size"
    if pixel_size is None:
        pixel_size = movie.pixel_size
    if pixel_size is None:
        raise BayespsfInputError(
            "pixel_size: the movie's metadata has none; state it (nm): pixel_size= from "
            "Python, --pixel-size on the command line, or [geometry] pixel_size in the camera "
            "file"
        )
    if pixel_size == movie.pixel_size and "pixel_size_field" in movie.metadata:
        source = (
            f"from the {movie.metadata['pixel_size']} metadata of {movie.path}: "
            f"{movie.metadata['pixel_size_field']}"
        )
    psf.check_geometry(1, pixel_size)  # a finite number > 0
    return check_pixel_size(pixel_size, source)
