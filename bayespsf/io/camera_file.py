"""The camera file: a TOML file with the ``[camera]`` table of scenes (its ``kind`` and, for
that kind, every key of ``CAMERA_KEYS``), ``[geometry] pixel_size`` and, optionally,
``[emitter]`` and ``[prior]``.

``bayespsf calibrate`` writes one (``camera_file_text``, with its provenance as comments);
``bayespsf fit --camera``, ``detect``, ``analyze`` and ``calibrate-z`` read one
(``read_camera_file``) and turn it into the scene of their ROIs (``camera_scene``). The counts'
units depend on the camera, so a file without its camera table, kind or a key of that kind is
an error, never a default (a default gain would scale every posterior SD).
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path

from bayespsf.errors import BayespsfInputError
from bayespsf.scene import Scene, SceneError

#: What a camera file must state for its kind: the counts' units depend on it.
CAMERA_KEYS = {
    "photon": (),
    "emccd": ("gain", "offset", "readout_sd", "e_per_adu"),
    "scmos": ("gain", "offset", "variance"),
}


def read_camera_file(path: str | os.PathLike) -> dict:
    """The tables of a camera file.

    Parameters
    ----------
    path : str or path-like
        The camera file (TOML): ``[camera]`` with an explicit ``kind`` and, for that kind,
        every key of ``CAMERA_KEYS``; ``[geometry] pixel_size``, ``[emitter]`` and
        ``[prior]`` optional.

    Returns
    -------
    dict
        The file's tables as ``tomllib`` reads them, unchanged.

    Raises
    ------
    BayespsfInputError
        If the file cannot be read as TOML, has no ``[camera]`` table with a ``kind``, lacks a
        key its kind needs, or has a ``[geometry]``, ``[emitter]`` or ``[prior]`` that is not
        a table. A missing camera table, kind or key is never assumed: the counts' units
        depend on them.
    """
    try:
        table = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise BayespsfInputError(f"{path}: cannot read it as a camera file ({exc})") from exc
    camera = table.get("camera")
    if not isinstance(camera, dict) or "kind" not in camera:
        raise BayespsfInputError(
            f"{path}: no [camera] table with its kind ('emccd', 'scmos' or 'photon', "
            "and the gain, offset and readout noise of the counts); the counts' units depend "
            "on it, so it is never assumed"
        )
    missing = [k for k in CAMERA_KEYS.get(camera["kind"], ()) if k not in camera]
    if missing:
        raise BayespsfInputError(
            f"{path}: [camera] of kind {camera['kind']!r} must state "
            f"{', '.join(missing)} (a `bayespsf calibrate` camera file states them all)"
        )
    for section in ("geometry", "emitter", "prior"):
        if not isinstance(table.get(section, {}), dict):
            raise BayespsfInputError(f"{path}: [{section}] must be a table")
    return table


def camera_scene(
    table: Mapping,
    path: str | os.PathLike,
    roi: int,
    pixel_size: float | None = None,
    *,
    roi_name: str = "the ROIs' side",
) -> Scene:
    """The scene of a camera file's tables for ROIs of side ``roi``.

    Parameters
    ----------
    table : mapping
        The camera file's tables, as ``read_camera_file`` returns them (not modified).
    path : str or path-like
        The camera file, to name in error messages.
    roi : int
        The side of the ROIs in pixels (the scene's ``[geometry] roi``).
    pixel_size : float, optional
        The pixel size in nm (a movie's metadata), used where the file gives none.
    roi_name : str, default "the ROIs' side"
        What gives ``roi``, to name in messages: ``"--fit"`` for the movie commands, whose
        message then offers that flag too.

    Returns
    -------
    Scene
        The scene of the file's tables with ``geometry.roi = roi``.

    Raises
    ------
    BayespsfInputError
        If neither the file nor ``pixel_size`` gives a pixel size, or the file states a
        ``[geometry] roi`` other than ``roi`` (naming both); the scene's own checks raise
        ``SceneError`` for values out of range.
    """
    table = {**table, "geometry": dict(table.get("geometry", {}))}
    geometry = table["geometry"]
    if "pixel_size" not in geometry and pixel_size is not None:
        geometry["pixel_size"] = pixel_size
    if "pixel_size" not in geometry:
        raise BayespsfInputError(f"{path}: no [geometry] pixel_size (nm)")
    stated = geometry.get("roi", roi)
    if isinstance(stated, bool) or stated != roi:
        flag = f", or give {roi_name} {stated!r}" if roi_name.startswith("--") else ""
        raise BayespsfInputError(
            f"{path}: [geometry] roi = {stated!r}, but {roi_name} is {roi}: set [geometry] "
            f"roi = {roi} in {path} or remove that key ({roi_name} then gives it){flag}"
        )
    geometry["roi"] = roi
    try:
        return Scene.from_dict(table)
    except SceneError as exc:  # the file to mend, and that it is read as a scene's tables
        raise SceneError(f"{path}: {exc} (a camera file holds a scene's tables)") from None


def camera_file_text(tables: Mapping[str, Mapping], comments: Sequence[str] = ()) -> str:
    """The text of a camera file: comment lines, then each table with its keys in order.

    Parameters
    ----------
    tables : mapping of str to mapping
        The tables to write, in order (for example ``geometry`` with ``pixel_size``, then
        ``camera``); strings are written in double quotes, other values by their ``repr``.
    comments : sequence of str, optional
        Lines written first, each after ``"# "`` (the file's provenance), then a blank line.

    Returns
    -------
    str
        The file's text, ending in a newline.
    """
    lines = [f"# {comment}" for comment in comments]
    if lines:
        lines.append("")
    for number, (name, table) in enumerate(tables.items()):
        if number:
            lines.append("")
        lines.append(f"[{name}]")
        lines += [
            f'{key} = "{value}"' if isinstance(value, str) else f"{key} = {value!r}"
            for key, value in table.items()
        ]
    return "\n".join(lines) + "\n"


def write_camera_file(
    tables: Mapping[str, Mapping], path: str | os.PathLike, comments: Sequence[str] = ()
) -> Path:
    """Write a camera file (``camera_file_text``) that ``read_camera_file`` reads.

    Parameters
    ----------
    tables : mapping of str to mapping
        The tables to write, in order (``camera_file_text``).
    path : str or path-like
        The file to write; its folder must exist.
    comments : sequence of str, optional
        Comment lines written first (``camera_file_text``).

    Returns
    -------
    Path
        The file written.
    """
    path = Path(path)
    path.write_text(camera_file_text(tables, comments), encoding="utf-8")
    return path


__all__ = [
    "CAMERA_KEYS",
    "camera_file_text",
    "camera_scene",
    "read_camera_file",
    "write_camera_file",
]
