"""The interface every camera implements (in the spirit of ``scipy.stats``: ``logpdf``/``rvs``).

A camera turns expected photons per pixel (``expected``, >= 0) into counts in ADU. Its three
public methods validate their input and broadcast over leading batch dimensions; subclasses
implement the unchecked ``_log_likelihood`` / ``_sample`` / ``_fisher_information`` that hot
loops (the vectorised log-posterior) may call after validating once.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from bayespsf._checks import as_generator, broadcast_pair, finite_array, nonnegative_array


class Camera(ABC):
    """Base class: the law of a pixel's counts (ADU) given its expected photons."""

    fisher_methods: tuple[str, ...] = ("exact",)  # what fisher_information(method=) accepts

    def log_likelihood(self, counts, expected) -> np.ndarray:
        """Element-wise log p(counts | expected), broadcasting ``counts`` against ``expected``.

        ``counts`` in ADU (finite), ``expected`` in photons (finite, >= 0). Values outside the
        law's support give ``-inf``; bad input raises ``ValueError`` naming the argument.
        """
        c = finite_array("counts", counts)
        lam = nonnegative_array("expected", expected)
        c, lam = broadcast_pair("counts", c, "expected", lam)
        self._check_counts(c)
        return self._log_likelihood(c, lam)

    def sample(self, expected, rng) -> np.ndarray:
        """Counts in ADU drawn from the law, same shape as ``expected``.

        ``rng`` is a ``numpy.random.Generator`` or an integer seed.
        """
        lam = nonnegative_array("expected", expected)
        return self._sample(lam, as_generator(rng))

    def fisher_information(self, expected) -> np.ndarray:
        """Per-pixel Fisher information about the expected photons, ``E[(d log p / d lam)^2]``."""
        lam = nonnegative_array("expected", expected)
        return self._fisher_information(lam)

    def score(self, counts, expected) -> np.ndarray:
        """Element-wise ``d log p(counts | expected) / d expected`` (the gradient the maximum
        likelihood fit and the sampler's start use)."""
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

    def _step_information(self, expected: np.ndarray) -> np.ndarray:
        """Per-pixel information that steers an optimiser's steps (the stack MLE's metric),
        where only its scale and shape matter, not its last digits: the Fisher information
        unless a camera has a much cheaper close bound."""
        return self._fisher_information(expected)

    def variance(self, expected) -> np.ndarray:
        """Variance of the counts, in ADU^2, given expected photons (its exact second moment)."""
        return self._variance(nonnegative_array("expected", expected))

    @abstractmethod
    def _variance(self, expected: np.ndarray) -> np.ndarray: ...

    @abstractmethod
    def photons_per_adu(self):
        """Mean photons per ADU above the offset (scalar or per-pixel map), and the offset:
        ``(counts - offset) * photons_per_adu`` is the photon estimate the paper fits."""

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
        """The camera's parameters, enough to rebuild it (scenes, result files)."""
