"""How the spot's widths change with the emitter's axial position z (issue 16, item 1).

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
from dataclasses import dataclass

import numpy as np

from bayespsf._checks import finite_array, scalar_in_range
from bayespsf.errors import BayespsfInputError


@dataclass(frozen=True)
class HuangCurve:
    """``w(z) = w0 sqrt(1 + u^2 + A u^3 + B u^4)``, ``u = (z - c) / d`` (module docstring)."""

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

    def width(self, z) -> np.ndarray:
        _, alpha = self._alpha(z)
        return self.w0 * self._shape(alpha)

    def slope(self, z) -> np.ndarray:
        """``dw/dz = w0 (2u + 3A u^2 + 4B u^3) / (2 d sqrt(alpha))``."""
        u, alpha = self._alpha(z)
        return (
            self.w0
            * (2 * u + 3 * self.A * u**2 + 4 * self.B * u**3)
            / (2 * self.d * np.sqrt(alpha))
        )

    def even_plane(self) -> float | None:
        """The plane about which the width is even (``c`` when ``A = 0``), or None."""
        return self.c if self.A == 0.0 else None


@dataclass(frozen=True)
class PolynomialCurve(HuangCurve):
    """``w(z) = w0 (1 + u^2 + A u^3 + B u^4)``, ``u = (z - c) / d`` (module docstring)."""

    kind = "polynomial"

    @staticmethod
    def _shape(alpha):
        return alpha

    def slope(self, z) -> np.ndarray:
        """``dw/dz = w0 (2u + 3A u^2 + 4B u^3) / d``."""
        u, _ = self._alpha(z)
        return self.w0 * (2 * u + 3 * self.A * u**2 + 4 * self.B * u**3) / self.d


def widths_of_terms(kind: type[HuangCurve], terms: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The width at each ``z`` (n,) of curves of class ``kind`` with per-row terms ``terms``
    (n, 5: w0 c d A B), unchecked: NaN where a row's curve is undefined (calibration draws,
    ``bayespsf.axial.posterior``)."""
    w0, c, d, a, b = np.moveaxis(np.asarray(terms, dtype=np.float64), -1, 0)
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        u = (z - c) / d
        alpha = 1.0 + u**2 + a * u**3 + b * u**4
        ok = np.isfinite(alpha) & (alpha > 0) & (d > 0) & (w0 > 0)
        return np.where(ok, w0 * kind._shape(np.where(ok, alpha, 1.0)), np.nan)


@dataclass(frozen=True)
class Defocus:
    """The widths (s_x, s_y) of a spot at axial position z: one ``HuangCurve`` per axis."""

    x: HuangCurve  # or PolynomialCurve
    y: HuangCurve

    @classmethod
    def symmetric(cls, s0: float, depth: float = 400.0) -> Defocus:
        """The paper's ``s(z) = s0 sqrt(1 + (z / D)^2)`` on both axes."""
        s0 = scalar_in_range("s0", s0, 0.0, low_inclusive=False)
        curve = HuangCurve(s0, 0.0, scalar_in_range("depth", depth, 0.0, low_inclusive=False))
        return cls(curve, curve)

    @classmethod
    def astigmatic(cls, w0: float, separation: float, depth: float, A: float = 0.0,
                   B: float = 0.0) -> Defocus:  # fmt: skip
        """Both axes of in-focus width ``w0`` and depth ``depth``, x in focus at
        ``-separation / 2`` and y at ``+separation / 2``; ``A`` and ``B`` on both (with y's
        odd term mirrored, so that the two curves are mirror images about z = 0)."""
        half = 0.5 * scalar_in_range("separation", separation, 0.0, np.inf)
        depth = scalar_in_range("depth", depth, 0.0, low_inclusive=False)
        return cls(HuangCurve(w0, -half, depth, A, B), HuangCurve(w0, half, depth, -A, B))

    @classmethod
    def from_table(cls, table: Mapping, s0x: float, s0y: float) -> Defocus:
        """The defocus of a scene's ``[axial]`` table (``bayespsf.scene_schema``), with the
        emitter's in-focus widths ``s0x``, ``s0y``."""
        if table["curve"] == "symmetric":
            curves = [HuangCurve(s0, 0.0, table["depth"]) for s0 in (s0x, s0y)]
            return cls(*curves)
        kind = HuangCurve if table["curve"] == "huang" else PolynomialCurve
        return cls(*(
            kind(s0, table[f"focus_{axis}"], table[f"depth_{axis}"], table[f"A_{axis}"],
                 table[f"B_{axis}"])
            for axis, s0 in (("x", s0x), ("y", s0y))
        ))  # fmt: skip

    @classmethod
    def from_scene(cls, scene) -> Defocus:
        """The defocus a ``Scene`` declares in ``[axial]``, with its emitter's in-focus
        widths."""
        if "axial" not in scene.to_dict():
            raise BayespsfInputError("the scene declares no [axial] table: no defocus")
        return cls.from_table(scene.axial, scene.emitter["s0x"], scene.emitter["s0y"])

    def widths(self, z) -> tuple[np.ndarray, np.ndarray]:
        return self.x.width(z), self.y.width(z)

    def slopes(self, z) -> tuple[np.ndarray, np.ndarray]:
        return self.x.slope(z), self.y.slope(z)


__all__ = ["Defocus", "HuangCurve", "PolynomialCurve", "widths_of_terms"]
