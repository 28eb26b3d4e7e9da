"""Ideal photon counting: counts are photons, Poisson distributed."""

from __future__ import annotations

import numpy as np
from scipy import special

from bayespsf.cameras.base import Camera
from bayespsf.errors import BayespsfInputError

# the likelihood tiers a scene may name for a photon counter: both are its one Poisson law
TIERS = ("exact", "poisson")


def poisson_log_pmf(k, lam):
    """``k log lam - lam - log k!`` for ``k >= 0`` (real ``k`` through ``gammaln``), ``lam >= 0``.

    ``xlogy`` gives the right limit ``0 log 0 = 0`` when ``lam == 0``.
    """
    return special.xlogy(k, lam) - lam - special.gammaln(k + 1.0)


def poisson_score(k, lam):
    """``d/dlam`` of ``poisson_log_pmf``: ``k / lam - 1``, and ``-1`` at ``k == 0``.

    At ``lam == 0`` with ``k > 0`` it is the one-sided derivative ``+inf``; below
    ``lam ~ k * 1e-308`` the true value exceeds the double range and is ``+inf`` too (no
    warning: both are the correctly rounded value).
    """
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        return np.where(k == 0, -1.0, k / lam - 1.0)


class Photon(Camera):
    """An ideal photon-counting detector: ``counts ~ Poisson(expected)``, 1 ADU per photon.

    It takes no parameters: no gain, no offset, no readout.

    See Also
    --------
    EMCCD, SCMOS : cameras with gain and readout noise.

    Notes
    -----
    Counts must be non-negative integers (``log_likelihood`` raises
    ``BayespsfInputError`` otherwise). The Fisher information is ``1 / lam`` (infinite at
    ``lam == 0``) and the variance ``lam``.

    Examples
    --------
    >>> import numpy as np
    >>> from bayespsf.cameras import Photon
    >>> camera = Photon()
    >>> camera.sample(np.full(3, 5.0), rng=1).shape
    (3,)
    >>> camera.fisher_information([1.0, 4.0])
    array([1.  , 0.25])
    """

    def check_counts(self, counts):
        if np.any(counts < 0) or np.any(counts != np.round(counts)):
            raise BayespsfInputError(
                "counts must be non-negative integers (photons) for the Photon camera"
            )

    def log_likelihood_unchecked(self, counts, expected):
        return poisson_log_pmf(counts, expected)

    def _sample(self, expected, rng):
        return rng.poisson(expected).astype(np.float64)

    def score_unchecked(self, counts, expected):
        """``k / lam - 1`` (``-1`` where ``k == 0``): ``poisson_score``.

        Parameters
        ----------
        counts, expected : ndarray
            As ``Camera.log_likelihood_unchecked``.

        Returns
        -------
        ndarray
            ``d log p / d lam`` per photon, the arguments' shape.
        """
        return poisson_score(counts, expected)

    def _variance(self, expected):
        return expected.copy()

    def photons_per_adu(self):
        return 1.0, 0.0

    def fisher_information_unchecked(self, expected):
        """``1 / lam`` (infinite at ``lam == 0``).

        Parameters
        ----------
        expected : ndarray
            Expected photoelectrons per pixel.

        Returns
        -------
        ndarray
            Per photon^2, the shape of ``expected``.
        """
        with np.errstate(divide="ignore"):
            return 1.0 / expected

    def to_dict(self):
        return {"kind": "photon"}

    def __repr__(self):
        return "Photon()"
