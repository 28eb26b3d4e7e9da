"""The interface every camera implements (in the spirit of ``scipy.stats``: ``logpdf``/``rvs``).

A camera turns expected photons per pixel (``expected``, >= 0) into counts in ADU. Its three
public methods validate their input and broadcast over leading batch dimensions; subclasses
implement the unchecked ``_log_likelihood`` / ``_sample`` / ``_fisher_information`` that hot
loops (the vectorised log-posterior) may call after validating once.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import ArrayLike

from bayespsf._validate import as_generator, broadcast_pair, finite_array, nonnegative_array


class Camera(ABC):
    """Base class: the law of a pixel's counts (ADU) given its expected photons.

    Attributes
    ----------
    fisher_methods : tuple of str
        The ``method`` values ``fisher_information`` accepts (``("exact",)`` by default).

    See Also
    --------
    Photon, EMCCD, SCMOS : the camera laws.

    Notes
    -----
    Subclasses implement the unchecked ``_log_likelihood``, ``_sample``,
    ``_fisher_information`` and ``_variance`` and the public ``photons_per_adu`` and
    ``to_dict``; the public methods here validate their input once and call them.
    """

    fisher_methods: tuple[str, ...] = ("exact",)  # what fisher_information(method=) accepts

    def log_likelihood(self, counts: ArrayLike, expected: ArrayLike) -> np.ndarray:
        """Element-wise log p(counts | expected), broadcasting ``counts`` against ``expected``.

        Parameters
        ----------
        counts : array_like
            Counts in ADU, finite.
        expected : array_like
            Expected photons (photoelectrons) per pixel, finite and >= 0.

        Returns
        -------
        ndarray
            Log probability (density per ADU for continuous laws), the broadcast shape of
            ``counts`` and ``expected``; ``-inf`` outside the law's support.

        Raises
        ------
        BayespsfInputError
            If an argument is not finite, ``expected`` is negative, the shapes do not
            broadcast, or ``counts`` is outside the camera's domain (the message names the
            argument).

        See Also
        --------
        sample : draws from the same law.
        score : the derivative by ``expected``.

        Examples
        --------
        >>> from bayespsf.cameras import Photon
        >>> Photon().log_likelihood([0, 1, 2], expected=1.0).round(4)
        array([-1.    , -1.    , -1.6931])
        """
        c = finite_array("counts", counts)
        lam = nonnegative_array("expected", expected)
        c, lam = broadcast_pair("counts", c, "expected", lam)
        self._check_counts(c)
        return self._log_likelihood(c, lam)

    def sample(self, expected: ArrayLike, rng: np.random.Generator | int) -> np.ndarray:
        """Counts in ADU drawn from the law.

        Parameters
        ----------
        expected : array_like
            Expected photons (photoelectrons) per pixel, finite and >= 0.
        rng : numpy.random.Generator or int
            The random generator, or an integer seed for one.

        Returns
        -------
        ndarray
            Counts in ADU (float64), the shape of ``expected``.

        Raises
        ------
        BayespsfInputError
            If ``expected`` is not finite or is negative.

        See Also
        --------
        log_likelihood : the law's log probability.
        """
        lam = nonnegative_array("expected", expected)
        return self._sample(lam, as_generator(rng))

    def fisher_information(self, expected: ArrayLike) -> np.ndarray:
        """Per-pixel Fisher information about the expected photons.

        Parameters
        ----------
        expected : array_like
            Expected photons (photoelectrons) per pixel ``lam``, finite and >= 0.

        Returns
        -------
        ndarray
            ``E[(d log p / d lam)^2]`` per photon^2, the shape of ``expected``.

        Raises
        ------
        BayespsfInputError
            If ``expected`` is not finite or is negative.

        See Also
        --------
        bayespsf.theory.fisher_matrix : the information about the six spot parameters.
        """
        lam = nonnegative_array("expected", expected)
        return self._fisher_information(lam)

    def score(self, counts: ArrayLike, expected: ArrayLike) -> np.ndarray:
        """Element-wise ``d log p(counts | expected) / d expected``.

        The gradient the maximum likelihood fit and the sampler's start use.

        Parameters
        ----------
        counts : array_like
            Counts in ADU, finite.
        expected : array_like
            Expected photons (photoelectrons) per pixel, finite and >= 0.

        Returns
        -------
        ndarray
            The derivative per photon, the broadcast shape of the two arguments.

        Raises
        ------
        BayespsfInputError
            For the inputs ``log_likelihood`` refuses.
        """
        c = finite_array("counts", counts)
        lam = nonnegative_array("expected", expected)
        c, lam = broadcast_pair("counts", c, "expected", lam)
        self._check_counts(c)
        return self._score(c, lam)

    def _score(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray:
        """Central difference of the log-likelihood (step 1e-5 of lam + 1e-3), forward
        difference where lam is smaller than the step. Cameras with a closed form override.
        NaN where the count has zero density at both ends (outside the tier's support)."""
        h = 1e-5 * (expected + 1e-3)
        low = np.maximum(expected - h, 0.0)
        high = expected + h
        up, down = self._log_likelihood(counts, high), self._log_likelihood(counts, low)
        with np.errstate(invalid="ignore"):  # -inf - -inf: no density, no derivative
            return (up - down) / (high - low)

    def _log_likelihood_and_score(self, counts: np.ndarray, expected: np.ndarray):
        """``(_log_likelihood, _score)`` at once, for loops that need both at the same point
        (the stack MLE); cameras that can share work between the two override it."""
        return self._log_likelihood(counts, expected), self._score(counts, expected)

    def _score_and_curvature(self, counts: np.ndarray, expected: np.ndarray):
        """``_score`` and its derivative by lam, the law's curvature (the observed
        information's): a central difference of the score, ``1e-4 max(lam, 1)`` each way
        (forward where that would go below 0; near ``lam = 0``, no background, a secant over
        1e-4 photons, where the law's tangent curvature is unbounded). Cameras with it in
        closed form override."""
        step = 1e-4 * np.maximum(expected, 1.0)
        low, high = np.maximum(expected - step, 0.0), expected + step
        curvature = (self._score(counts, high) - self._score(counts, low)) / (high - low)
        return self._score(counts, expected), curvature

    def _step_information(self, expected: np.ndarray) -> np.ndarray:
        """Per-pixel information that steers an optimiser's steps (the stack MLE's metric),
        where only its scale and shape matter, not its last digits: the Fisher information
        unless a camera has a much cheaper close bound, or the tier scored is not the camera's
        law (the EMCCD's ``poisson`` tier: its own)."""
        return self._fisher_information(expected)

    def variance(self, expected: ArrayLike) -> np.ndarray:
        """Variance of the counts given expected photons (the law's exact second moment).

        Parameters
        ----------
        expected : array_like
            Expected photons (photoelectrons) per pixel, finite and >= 0.

        Returns
        -------
        ndarray
            Variance in ADU^2, the shape of ``expected`` (broadcast against per-pixel maps).

        Raises
        ------
        BayespsfInputError
            If ``expected`` is not finite or is negative.
        """
        return self._variance(nonnegative_array("expected", expected))

    @abstractmethod
    def _variance(self, expected: np.ndarray) -> np.ndarray: ...

    @abstractmethod
    def photons_per_adu(self) -> tuple[float | np.ndarray, float | np.ndarray]:
        """Mean photons per ADU above the offset, and the offset.

        Returns
        -------
        photons_per_adu : float or ndarray
            Photons (photoelectrons) per ADU, a scalar or a per-pixel map.
        offset : float or ndarray
            The offset in ADU: ``(counts - offset) * photons_per_adu`` is the photon estimate
            the paper fits.
        """

    def _check_counts(self, counts: np.ndarray) -> None:  # noqa: B027 (optional hook)
        """Hook for cameras whose counts have a restricted domain; the default accepts all."""

    @abstractmethod
    def _log_likelihood(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray: ...

    @abstractmethod
    def _sample(self, expected: np.ndarray, rng: np.random.Generator) -> np.ndarray: ...

    @abstractmethod
    def _fisher_information(self, expected: np.ndarray) -> np.ndarray: ...

    @abstractmethod
    def to_dict(self) -> dict:
        """The camera's parameters, enough to rebuild it (scenes, result files).

        Returns
        -------
        dict
            ``kind`` and the constructor's arguments.
        """
