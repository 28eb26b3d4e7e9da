"""Checks across the keys of a scene's optional tables ([axial], [movie]), which a key's own
range cannot make: ``check_sections`` runs them when a scene is read."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from bayespsf.errors import BayespsfInputError
from bayespsf.psf import Defocus
from bayespsf.scene.key import SceneError


def check_sections(d: Mapping) -> None:
    """Raise ``SceneError`` where the declared optional tables' keys contradict each other.

    Parameters
    ----------
    d : mapping
        The scene's tables, each key checked on its own and defaults filled in.

    Raises
    ------
    SceneError
        An [axial] table without the Gaussian PSF or with a z range on which its width curves
        are not defined; a [movie] whose photon range runs backwards (``photons_low`` above
        ``photons_high``, a 0 standing for ``emitter.photons``).
    """
    if "axial" in d:
        _check_axial(d)
    if "movie" in d:
        m, photons = d["movie"], d["emitter"]["photons"]
        low, high = m["photons_low"] or photons, m["photons_high"] or photons
        if low > high:
            raise SceneError(
                f"movie.photons_low ({low:g}) must not be above movie.photons_high ({high:g}) "
                "(a 0 stands for emitter.photons); swap them, or declare the range's other end"
            )


def _check_axial(d: Mapping) -> None:
    """The [axial] table needs the Gaussian PSF (its widths follow z) and a z range on which
    both curves are defined (1 + u^2 + A u^3 + B u^4 > 0)."""
    ax = d["axial"]
    if d["optics"]["psf"] != "gaussian":
        raise SceneError("[axial] needs optics.psf = 'gaussian': the Airy pattern is in focus only")
    if ax["z"] == "uniform" and not ax["z_low"] < ax["z_high"]:
        raise SceneError(
            f"axial.z_low must be below axial.z_high, got {ax['z_low']:g} and {ax['z_high']:g}"
        )
    low, high = {
        "fixed": (ax.get("z0"), ax.get("z0")),
        "uniform": (ax.get("z_low"), ax.get("z_high")),
        "normal": (
            ax.get("z0", 0.0) - 6 * ax.get("z_sd", 0.0),
            ax.get("z0", 0.0) + 6 * ax.get("z_sd", 0.0),
        ),
    }[ax["z"]]
    e = d["emitter"]
    defocus = Defocus.from_table(ax, e["s0x"], e["s0y"])
    try:
        defocus.widths(np.linspace(low, high, 2001))
    except BayespsfInputError as exc:
        raise SceneError(f"[axial]: {exc} (the z range the scene draws from)") from None


__all__ = ["check_sections"]
