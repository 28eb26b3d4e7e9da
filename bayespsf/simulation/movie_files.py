"""A simulated movie's tables and files: the columns of its molecule and truth tables
(``MOLECULE_COLUMNS``, ``TRUTH_COLUMNS``) and the writer behind ``simulate_movie(scene, seed,
out=STEM)``: frames as OME-TIFF pages written one at a time, tables as CSV."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf.scene import Scene

MOLECULE_COLUMNS = (
    "molecule",
    "x",
    "y",
    "x_nm",
    "y_nm",
    "s_x",
    "s_y",
    "photons",
    "fluorophores",
    "bleach_frame",
    "moving",
    "photon_unit",
)
TRUTH_COLUMNS = ("molecule", "frame", "x", "y", "photons", "on", "fluorophores_on", "photon_unit")


def _write(scene, stem: Path, molecules, frames, dark, dtype) -> dict[str, Path]:
    """Write ``STEM.ome.tif``, ``STEM.molecules.csv``, ``STEM.truth.csv`` and, with dark
    frames, ``STEM.dark.ome.tif``, consuming the ``(counts, truth)`` pairs of ``frames`` one at
    a time; returns the paths by role (``MovieTruth.files``)."""
    m = scene.movie
    files = {
        "movie": stem.with_name(stem.name + ".ome.tif"),
        "molecules": stem.with_name(stem.name + ".molecules.csv"),
        "truth": stem.with_name(stem.name + ".truth.csv"),
    }
    stem.parent.mkdir(parents=True, exist_ok=True)
    molecules.to_csv(files["molecules"], index=False)
    with open(files["truth"], "w", newline="") as table:
        pd.DataFrame(columns=list(TRUTH_COLUMNS)).to_csv(table, index=False)

        def pages():
            for counts, truth in frames:
                truth.to_csv(table, index=False, header=False)
                yield counts

        _write_tiff(files["movie"], pages(), m["frames"], scene, dtype)
    if m["dark_frames"]:
        files["dark"] = stem.with_name(stem.name + ".dark.ome.tif")
        _write_tiff(files["dark"], dark, m["dark_frames"], scene, dtype)
    return files


def _write_tiff(path: Path, pages, n: int, scene: Scene, dtype: np.dtype) -> None:
    """``n`` pages of ``dtype`` as one OME-TIFF (BigTIFF beyond 2 GiB), with the pixel size in
    µm and, when declared, ``movie.exposure`` as the time increment."""
    import tifffile

    m, a_um = scene.movie, scene.geometry["pixel_size"] / 1000.0
    metadata = {
        "axes": "TYX",
        "PhysicalSizeX": a_um,
        "PhysicalSizeXUnit": "µm",
        "PhysicalSizeY": a_um,
        "PhysicalSizeYUnit": "µm",
    }
    if m["exposure"] > 0:
        metadata.update(TimeIncrement=m["exposure"], TimeIncrementUnit="s")
    shape = (n, m["height"], m["width"])
    bigtiff = math.prod(shape) * dtype.itemsize > 2**31
    with tifffile.TiffWriter(path, bigtiff=bigtiff, ome=True) as tif:
        tif.write(pages, shape=shape, dtype=dtype, photometric="minisblack", metadata=metadata)
