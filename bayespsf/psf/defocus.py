"""How the spot's widths change with the emitter's axial position z.

One axis follows the defocus curve of Huang, Wang, Bates & Zhuang, Science 319 (2008):

    w(z) = w0 sqrt(1 + u^2 + A u^3 + B u^4),   u = (z - c) / d,

with w0 the in-focus width, c that axis's focal plane, d the depth of focus and A, B the
higher-order terms (``HuangCurve``), or its polynomial alternative

    w(z) = w0 (1 + u^2 + A u^3 + B u^4)

(``PolynomialCurve``; with A = B = 0 the parabola ``a (z - c)^2 + b`` of ThunderSTORM's first
calibration model, Ovesny et al., Bioinformatics 30 (2014)). ``Defocus`` pairs two curves,
one per axis:

* ``Defocus.symmetric(s0, depth)``: both axes in focus at z = 0 with ``A = B = 0``. This is
  the curve ``s(z) = s0 sqrt(1 + (z / D)^2)`` of DeSantis, DeCenzo, Li & Wang, Opt. Express 18
  (2010), Discussion (D ~ 400 nm): z and -z give the same image.
* ``Defocus.astigmatic(...)``: the axes focus at different planes (a cylindrical lens), so
  s_x and s_y change in opposite directions through focus and z has one answer.

Widths are in nm, z in nm.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike

from bayespsf._validate import finite_array, scalar_in_range
from bayespsf.errors import BayespsfInputError


@dataclass(frozen=True)
class HuangCurve:
    """One axis's width against z: ``w(z) = w0 sqrt(1 + u^2 + A u^3 + B u^4)``.

    Parameters
    ----------
    w0 : float
        In-focus width in nm, > 0.
    c : float, optional
        That axis's focal plane in nm (default 0).
    d : float, optional
        Depth of focus in nm, > 0 (default 400); ``u = (z - c) / d``.
    A, B : float, optional
        Third- and fourth-order coefficients (default 0).

    Raises
    ------
    BayespsfInputError
        If a term is not a finite number or ``w0`` or ``d`` is not > 0.

    See Also
    --------
    PolynomialCurve : the same terms without the square root.
    Defocus : two curves, one per axis.

    Notes
    -----
    The defocus curve of Huang, Wang, Bates & Zhuang, Science 319 (2008); ``kind`` is
    ``"huang"``. The terms are stored as floats.

    Examples
    --------
    >>> from bayespsf.psf import HuangCurve
    >>> HuangCurve(w0=120.0, d=400.0).width([0.0, 400.0]).round(2)
    array([120.  , 169.71])
    """

    kind = "huang"

    w0: float
    c: float = 0.0
    d: float = 400.0
    A: float = 0.0
    B: float = 0.0

    def __post_init__(self):
        for name, low in (("w0", 0.0), ("d", 0.0), ("c", -np.inf), ("A", -np.inf), ("B", -np.inf)):
            value = scalar_in_range(name, getattr(self, name), low, low_inclusive=low == -np.inf)
            object.__setattr__(self, name, value)  # a float, whatever number was given

    def _alpha(self, z):
        z = finite_array("z", z)
        with np.errstate(over="ignore", invalid="ignore"):
            u = (z - self.c) / self.d
            alpha = 1.0 + u**2 + self.A * u**3 + self.B * u**4
        if not np.all(np.isfinite(alpha)):
            raise BayespsfInputError(
                f"z = {z[~np.isfinite(alpha)].ravel()[0]:g} nm is too many depths of focus "
                f"(d = {self.d:g} nm) from this curve's focus for its width to be a number"
            )
        if np.any(alpha <= 0):
            raise BayespsfInputError(
                f"z = {z[alpha <= 0].ravel()[0]:g} nm is outside this defocus curve's domain: "
                f"1 + u^2 + A u^3 + B u^4 <= 0 there (A = {self.A:g}, B = {self.B:g})"
            )
        return u, alpha

    @staticmethod
    def _shape(alpha):
        """The width over w0 as a function of ``alpha = 1 + u^2 + A u^3 + B u^4``."""
        return np.sqrt(alpha)

    def width(self, z: ArrayLike) -> np.ndarray:
        """The width at each axial position.

        Parameters
        ----------
        z : array_like
            Axial positions in nm (finite).

        Returns
        -------
        ndarray
            Widths in nm, the shape of ``z``.

        Raises
        ------
        BayespsfInputError
            If a ``z`` is outside the curve's domain (``1 + u^2 + A u^3 + B u^4 <= 0``, or
            too far from focus for the width to be a number).
        """
        _, alpha = self._alpha(z)
        return self.w0 * self._shape(alpha)

    def slope(self, z: ArrayLike) -> np.ndarray:
        """The derivative of the width by z.

        Parameters
        ----------
        z : array_like
            Axial positions in nm.

        Returns
        -------
        ndarray
            ``dw/dz = w0 (2u + 3A u^2 + 4B u^3) / (2 d sqrt(alpha))`` (nm per nm), the shape of
            ``z``; ``alpha = 1 + u^2 + A u^3 + B u^4``.

        Raises
        ------
        BayespsfInputError
            Where ``width`` does.
        """
        u, alpha = self._alpha(z)
        return (
            self.w0
            * (2 * u + 3 * self.A * u**2 + 4 * self.B * u**3)
            / (2 * self.d * np.sqrt(alpha))
        )

    def even_plane(self) -> float | None:
        """The plane about which the width is even.

        Returns
        -------
        float or None
            ``c`` (nm) when ``A = 0``, else None.
        """
        return self.c if self.A == 0.0 else None


@dataclass(frozen=True)
class PolynomialCurve(HuangCurve):
    """One axis's width against z: ``w(z) = w0 (1 + u^2 + A u^3 + B u^4)``.

    Parameters
    ----------
    w0, c, d, A, B : float
        As for ``HuangCurve``: in-focus width, focal plane and depth (nm; ``c``, ``d``, ``A``,
        ``B`` default to 0, 400, 0, 0), ``u = (z - c) / d``, and the higher-order terms.

    See Also
    --------
    HuangCurve : the same terms under a square root.

    Notes
    -----
    With ``A = B = 0`` this is the parabola ``a (z - c)^2 + b`` of ThunderSTORM's first
    calibration model (Ovesny et al., Bioinformatics 30 (2014)); ``kind`` is ``"polynomial"``.
    """

    kind = "polynomial"

    @staticmethod
    def _shape(alpha):
        return alpha

    def slope(self, z: ArrayLike) -> np.ndarray:
        """The derivative of the width by z.

        Parameters
        ----------
        z : array_like
            Axial positions in nm.

        Returns
        -------
        ndarray
            ``dw/dz = w0 (2u + 3A u^2 + 4B u^3) / d`` (nm per nm), the shape of ``z``.
        """
        u, _ = self._alpha(z)
        return self.w0 * (2 * u + 3 * self.A * u**2 + 4 * self.B * u**3) / self.d


def widths_of_terms(kind: type[HuangCurve], terms: ArrayLike, z: ArrayLike) -> np.ndarray:
    """The widths of many curves of one class, each at its own z, without checks.

    Parameters
    ----------
    kind : type
        ``HuangCurve`` or ``PolynomialCurve``.
    terms : array_like, shape (n, 5)
        One curve per row: ``w0 c d A B`` (``TERMS``; nm, nm, nm, -, -).
    z : array_like, shape (n,)
        Axial position of each row, nm.

    Returns
    -------
    ndarray, shape (n,)
        The width in nm of each row's curve at its ``z``; NaN where a row's curve is undefined.

    Notes
    -----
    Unchecked, for draws of a calibration's terms (``bayespsf.axial.posterior``).
    """
    w0, c, d, a, b = np.moveaxis(np.asarray(terms, dtype=np.float64), -1, 0)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        u = (z - c) / d
        alpha = 1.0 + u**2 + a * u**3 + b * u**4
        ok = np.isfinite(alpha) & (alpha > 0) & (d > 0) & (w0 > 0)
        return np.where(ok, w0 * kind._shape(np.where(ok, alpha, 1.0)), np.nan)


@dataclass(frozen=True)
class Defocus:
    """The widths (s_x, s_y) of a spot at axial position z: one curve per axis.

    Parameters
    ----------
    x : HuangCurve
        The curve of s_x (a ``HuangCurve`` or ``PolynomialCurve``).
    y : HuangCurve
        The curve of s_y.

    See Also
    --------
    HuangCurve, PolynomialCurve : the curves of one axis.

    Notes
    -----
    ``Defocus.symmetric(s0, depth)``: both axes in focus at z = 0 with ``A = B = 0``, the
    curve of the paper's Discussion: z and -z give the same image. ``Defocus.astigmatic``:
    the axes focus at different planes (a cylindrical lens), so z has one answer.

    Examples
    --------
    >>> from bayespsf.psf import Defocus
    >>> defocus = Defocus.astigmatic(w0=120.0, separation=400.0, depth=400.0)
    >>> [round(float(w), 1) for w in defocus.widths(200.0)]
    [169.7, 120.0]
    """

    x: HuangCurve  # or PolynomialCurve
    y: HuangCurve

    @classmethod
    def symmetric(cls, s0: float, depth: float = 400.0) -> Defocus:
        """The paper's ``s(z) = s0 sqrt(1 + (z / D)^2)`` on both axes.

        Parameters
        ----------
        s0 : float
            In-focus width of both axes, nm, > 0.
        depth : float, optional
            Depth of focus D in nm, > 0 (default 400, the paper's ~400 nm).

        Returns
        -------
        Defocus
            Both axes in focus at z = 0.

        Raises
        ------
        BayespsfInputError
            If ``s0`` or ``depth`` is not a finite number > 0.
        """
        s0 = scalar_in_range("s0", s0, 0.0, low_inclusive=False)
        curve = HuangCurve(s0, 0.0, scalar_in_range("depth", depth, 0.0, low_inclusive=False))
        return cls(curve, curve)

    @classmethod
    def astigmatic(
        cls, w0: float, separation: float, depth: float, A: float = 0.0, B: float = 0.0
    ) -> Defocus:
        """Two ``HuangCurve`` axes focused at different planes (a cylindrical lens).

        Parameters
        ----------
        w0 : float
            In-focus width of both axes, nm.
        separation : float
            Distance between the two focal planes, nm, >= 0: x is in focus at
            ``-separation / 2`` and y at ``+separation / 2``.
        depth : float
            Depth of focus of both axes, nm, > 0.
        A, B : float, optional
            Higher-order terms of both axes (y's odd term ``A`` mirrored, so that the two
            curves are mirror images about z = 0).

        Returns
        -------
        Defocus

        Raises
        ------
        BayespsfInputError
            If a term is out of its range.
        """
        half = 0.5 * scalar_in_range("separation", separation, 0.0, np.inf)
        depth = scalar_in_range("depth", depth, 0.0, low_inclusive=False)
        return cls(HuangCurve(w0, -half, depth, A, B), HuangCurve(w0, half, depth, -A, B))

    @classmethod
    def from_table(cls, table: Mapping, s0x: float, s0y: float) -> Defocus:
        """The defocus of a scene's ``[axial]`` table.

        Parameters
        ----------
        table : Mapping
            A normalised ``[axial]`` table (``bayespsf.scene.schema``): ``curve`` and its
            terms (``depth``, or ``focus_x``, ``depth_x``, ``A_x``, ``B_x`` and those of y).
        s0x, s0y : float
            The emitter's in-focus widths, nm.

        Returns
        -------
        Defocus
        """
        if table["curve"] == "symmetric":
            curves = [HuangCurve(s0, 0.0, table["depth"]) for s0 in (s0x, s0y)]
            return cls(*curves)
        kind = HuangCurve if table["curve"] == "huang" else PolynomialCurve
        return cls(
            *(
                kind(
                    s0,
                    table[f"focus_{axis}"],
                    table[f"depth_{axis}"],
                    table[f"A_{axis}"],
                    table[f"B_{axis}"],
                )
                for axis, s0 in (("x", s0x), ("y", s0y))
            )
        )

    @classmethod
    def from_scene(cls, scene) -> Defocus:
        """The defocus a ``Scene`` declares in ``[axial]``.

        Parameters
        ----------
        scene : Scene
            A scene with an ``[axial]`` table; its emitter's ``s0x``, ``s0y`` are the
            in-focus widths.

        Returns
        -------
        Defocus

        Raises
        ------
        BayespsfInputError
            If the scene declares no ``[axial]`` table.
        """
        if "axial" not in scene.to_dict():
            raise BayespsfInputError("the scene declares no [axial] table: no defocus")
        return cls.from_table(scene.axial, scene.emitter["s0x"], scene.emitter["s0y"])

    def widths(self, z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The widths of both axes at each axial position.

        Parameters
        ----------
        z : array_like
            Axial positions in nm.

        Returns
        -------
        s_x, s_y : ndarray
            Widths in nm, each the shape of ``z``.

        Raises
        ------
        BayespsfInputError
            If a ``z`` is outside either curve's domain.
        """
        return self.x.width(z), self.y.width(z)

    def slopes(self, z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The derivatives of both widths by z.

        Parameters
        ----------
        z : array_like
            Axial positions in nm.

        Returns
        -------
        ds_x_dz, ds_y_dz : ndarray
            Each the shape of ``z`` (nm per nm).
        """
        return self.x.slope(z), self.y.slope(z)


CURVES = {"huang": HuangCurve, "polynomial": PolynomialCurve}
TERMS = ("w0", "c", "d", "A", "B")
MISFIT_P = 1e-3  # a chi-square p-value below this says the curve does not fit the stack


@dataclass
class DefocusCalibration:
    """Fitted defocus curves with their uncertainty and how they were made.

    Parameters
    ----------
    curve : str
        The curve's kind, a key of ``CURVES`` (``"huang"`` or ``"polynomial"``).
    defocus : Defocus
        The fitted curves.
    fits : pandas.DataFrame
        One row per axis (index ``x``, ``y``): the terms ``w0 c d A B``, their SDs, ``chi2``,
        ``dof``, ``p``.
    covariance : dict of str to ndarray
        Per axis, the terms' covariance (5 x 5; rows and columns of terms held fixed are 0).
    steps : pandas.DataFrame
        The per-step widths the curves were fitted to.
    source : dict, optional
        Where the stack came from (free-form provenance, kept in every file and result).

    See Also
    --------
    bayespsf.axial.calibrate : makes one from a bead z-stack.
    """

    curve: str
    defocus: Defocus
    fits: pd.DataFrame
    covariance: dict[str, np.ndarray]
    steps: pd.DataFrame
    source: dict = field(default_factory=dict)

    def record(self) -> dict:
        """What a result that used this calibration keeps of it.

        Returns
        -------
        dict
            ``curve``, one entry per axis with its terms, ``chi2`` and ``p``, and ``source``
            (with the file it was loaded from).
        """
        axes = {
            axis: {k: float(v) for k, v in row[[*TERMS, "chi2", "p"]].items()}
            for axis, row in self.fits.iterrows()
        }
        return {"curve": self.curve, **axes, "source": dict(self.source)}

    @property
    def problems(self) -> list[str]:
        """One sentence per axis whose curve does not fit its stack (chi-square p below
        ``MISFIT_P``)."""
        out = []
        for axis, row in self.fits.iterrows():
            if row["p"] < MISFIT_P:
                out.append(
                    f"the {self.curve} curve does not fit the stack's {axis} widths: "
                    f"chi2 = {row['chi2']:.1f} on {int(row['dof'])} degrees of freedom "
                    f"(p = {row['p']:.1e}); residuals are beyond their errors, so z from this "
                    "curve will be biased where it is wrong"
                )
        return out


__all__ = [
    "CURVES",
    "TERMS",
    "Defocus",
    "DefocusCalibration",
    "HuangCurve",
    "PolynomialCurve",
    "widths_of_terms",
]
