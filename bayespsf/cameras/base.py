"""The interface every camera implements (in the spirit of ``scipy.stats``: ``logpdf``/``rvs``).

A camera turns expected photons per pixel (``expected``, >= 0) into counts in ADU. Its public
methods validate their input and broadcast over leading batch dimensions. Each law evaluation
has an ``*_unchecked`` twin (``log_likelihood_unchecked``, ``score_unchecked``, ...) that takes
arrays already validated and broadcast: the loops that evaluate the law thousands of times on
the same counts (the stack MLE, the samplers) check once (``check_counts``) and call those.
Subclasses implement the twins and the private ``_sample`` and ``_variance``.
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
    Subclasses implement ``log_likelihood_unchecked``, ``fisher_information_unchecked``,
    ``_sample``, ``_variance``, ``photons_per_adu`` and ``to_dict``, and ``check_counts`` where
    their counts have a restricted domain; they override ``score_unchecked`` (a central
    difference here), ``log_likelihood_and_score_unchecked``,
    ``score_and_curvature_unchecked`` and ``step_information_unchecked`` where they have
    closed forms or shared work. The public methods validate their input once and call the
    ``*_unchecked`` ones, which hot loops call directly after ``check_counts``.
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
        self.check_counts(c)
        return self.log_likelihood_unchecked(c, lam)

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
        return self.fisher_information_unchecked(lam)

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
        self.check_counts(c)
        return self.score_unchecked(c, lam)

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

    @abstractmethod
    def _sample(self, expected: np.ndarray, rng: np.random.Generator) -> np.ndarray: ...

    @abstractmethod
    def to_dict(self) -> dict:
        """The camera's parameters, enough to rebuild it (scenes, result files).

        Returns
        -------
        dict
            ``kind`` and the constructor's arguments.
        """

    def check_counts(self, counts: np.ndarray) -> None:  # noqa: B027 (optional hook)
        """Raise if finite ``counts`` lie outside the camera's domain (the default accepts all).

        The check the public methods make after validating finiteness: loops that call the
        ``*_unchecked`` methods on the same counts many times make it once.

        Parameters
        ----------
        counts : ndarray
            Counts in ADU, finite.

        Raises
        ------
        BayespsfInputError
            If a count is outside the domain (the message names it and the limit).
        """

    @abstractmethod
    def log_likelihood_unchecked(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray:
        """``log_likelihood`` of validated arrays of one shape, without checking them.

        Parameters
        ----------
        counts : ndarray
            Counts in ADU, finite and passed by ``check_counts``.
        expected : ndarray
            Expected photoelectrons per pixel, finite and >= 0, broadcast against ``counts``.

        Returns
        -------
        ndarray
            Element-wise log p, as ``log_likelihood``.
        """

    def score_unchecked(self, counts: np.ndarray, expected: np.ndarray) -> np.ndarray:
        """``score`` of validated arrays, without checking them.

        Here a central difference of the log-likelihood (step ``1e-5 (lam + 1e-3)``), forward
        where ``lam`` is below the step; cameras with a closed form override it.

        Parameters
        ----------
        counts, expected : ndarray
            As ``log_likelihood_unchecked``.

        Returns
        -------
        ndarray
            ``d log p / d expected`` per photon; NaN where the count has zero density at both
            ends of the difference (outside the tier's support).
        """
        h = 1e-5 * (expected + 1e-3)
        low = np.maximum(expected - h, 0.0)
        high = expected + h
        up = self.log_likelihood_unchecked(counts, high)
        down = self.log_likelihood_unchecked(counts, low)
        with np.errstate(invalid="ignore"):  # -inf - -inf: no density, no derivative
            return (up - down) / (high - low)

    def log_likelihood_and_score_unchecked(self, counts: np.ndarray, expected: np.ndarray):
        """``log_likelihood_unchecked`` and ``score_unchecked`` at once, for loops that need
        both at the same point (the stack MLE); cameras that share work between the two
        override it.

        Parameters
        ----------
        counts, expected : ndarray
            As ``log_likelihood_unchecked``.

        Returns
        -------
        log_p, score : ndarray
            The two, each of the arguments' shape.
        """
        return self.log_likelihood_unchecked(counts, expected), self.score_unchecked(
            counts, expected
        )

    def score_and_curvature_unchecked(self, counts: np.ndarray, expected: np.ndarray):
        """``score_unchecked`` and its derivative by ``expected``, the law's curvature (what
        the observed information is made of).

        Here a central difference of the score, ``1e-4 max(lam, 1)`` each way (forward where
        that would go below 0; near ``lam = 0``, no background, a secant over 1e-4 photons,
        where the law's tangent curvature is unbounded); cameras with it in closed form
        override it.

        Parameters
        ----------
        counts, expected : ndarray
            As ``log_likelihood_unchecked``.

        Returns
        -------
        score, curvature : ndarray
            ``d log p / d lam`` and ``d^2 log p / d lam^2``, each of the arguments' shape.
        """
        step = 1e-4 * np.maximum(expected, 1.0)
        low, high = np.maximum(expected - step, 0.0), expected + step
        change = self.score_unchecked(counts, high) - self.score_unchecked(counts, low)
        return self.score_unchecked(counts, expected), change / (high - low)

    @abstractmethod
    def fisher_information_unchecked(self, expected: np.ndarray) -> np.ndarray:
        """``fisher_information`` of validated ``expected`` (finite, >= 0), unchecked.

        Parameters
        ----------
        expected : ndarray
            Expected photoelectrons per pixel.

        Returns
        -------
        ndarray
            ``E[(d log p / d lam)^2]`` per photon^2, the shape of ``expected``.
        """

    def step_information_unchecked(self, expected: np.ndarray) -> np.ndarray:
        """Per-pixel information that steers an optimiser's steps (the stack MLE's metric).

        Only its scale and shape matter there, not its last digits: the Fisher information
        unless a camera has a much cheaper close bound, or the tier scored is not the camera's
        law (the EMCCD's ``poisson`` tier: its own).

        Parameters
        ----------
        expected : ndarray
            Expected photoelectrons per pixel, finite and > 0.

        Returns
        -------
        ndarray
            Information per photon^2, the shape of ``expected``.
        """
        return self.fisher_information_unchecked(expected)
