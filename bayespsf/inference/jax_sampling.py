"""The chain-free posteriors in JAX: ``sample_many(..., backend="jax")``.

The same methods as ``bayespsf.inference.batched`` (the Laplace where its pilot's weight SD
passes, Pareto-smoothed importance sampling from the Laplace Gaussian or Student-t where its
k-hat passes, else the emcee chain on the CPU), written as programs over chunks of ROIs
(``bayespsf.inference.jax_programs``), compiled once per draw count, so that a whole dataset
runs on one device:

* **Laplace** (``auto``, ``laplace``): ``PILOT`` Gaussian draws scored; the Laplace is taken
  where the normalised weights' SD is at most ``LAPLACE_WEIGHT_SD``; its draws are the first
  ``ess`` (rounded up to a multiple of ``CHAINS``) of ``2 ess`` Gaussian draws inside the
  prior's support.
* **The Laplace Gaussian** (``auto``): where the pilot's weight SD is above that but at most
  ``GAUSSIAN_WEIGHT_SD``, one round of Gaussian draws continuing the pilot, sized as the NumPy
  engine sizes it (the pilot's raw ESS per draw, with ``GAUSSIAN_MARGIN``) and rounded up to
  one of ``round_size``'s sizes (a fixed shape per size: few compilations). In the NumPy
  engine 99% of emccd-typical ROIs at N = 1 000 reach the ESS in that first batch; a ROI
  short of it, or whose k-hat fails, goes on to the Student-t.
* **Importance** (``auto``, ``importance``): rounds of Student-t draws (5 degrees of freedom,
  scaled by the Laplace covariance). The first round has ``first_batch(ess)`` draws; a ROI whose
  smoothed weights reach the ESS target is done. A ROI short of it gets a fresh round of twice
  the draws (fixed sizes, so that the programs a dataset needs compile once), up to
  ``MAX_ROUNDS`` rounds (520 to 8 320 draws at ESS 400) and ``50 ess`` draws; the weights of a
  round are those of its own draws (a round is independent of the decision to run it, so each
  round's estimate is valid on its own). This replaces the NumPy engine's growing batches,
  which a fixed-shape program cannot hold; the diagnostics and thresholds are the same. PSIS
  is ``bayespsf.inference.psis`` (``arviz_stats``' algorithm, array-generic), tested against
  ``arviz_stats``.
* Draws are scored with the camera law interpolated per pixel (``jax_fused``, within 1e-6 in
  log p per pixel); the ROIs whose interpolants miss their check run the same program again
  with the law itself (the same draws: they come from the ROI's key).
* Draws are resampled systematically to ``CHAINS * floor(ESS / CHAINS)`` equally weighted
  draws, and the summary row (mean, SD, quantiles, SBC rank) is computed on the device.

Random numbers come from JAX's counter-based generator keyed by each ROI's seed
(``sample_many``'s ``molecule_seed``), so a ROI's posterior does not depend on the chunk, the
chunk size or the device; it differs from the NumPy backend's draws by Monte Carlo error only.
"""

from __future__ import annotations

import functools

import numpy as np

from bayespsf.inference import jax_programs
from bayespsf.inference.backends import jax_modules, start_jax
from bayespsf.inference.batched import (
    GAUSSIAN_MARGIN,
    GAUSSIAN_WEIGHT_SD,
    LAPLACE_WEIGHT_SD,
    MAX_DRAWS_PER_ESS,
    PILOT,
    _choleskys,
    laplace_in_z,
)
from bayespsf.inference.importance import CHAINS, KHAT_MAX, MIN_BATCH, first_batch
from bayespsf.inference.jax_mle import bucket
from bayespsf.inference.jax_model import JaxModel
from bayespsf.inference.summary import QUANTILES

MAX_ROUNDS = 5  # importance rounds per ROI before the chain: the last 16x the first
DRAW_PIXELS = {"cpu": 2**23, "gpu": 2**26}  # draws x pixels per device call
ROUND_STEP = 2 ** (1 / 8)  # the Gaussian round's sizes: MIN_BATCH / 2 times its powers
KEY_ARGUMENT = {"pilot": 4, "laplace": 3, "gaussian": 4, "importance": 4}  # programs' keys


def seed_words(seeds) -> np.ndarray:
    """Each ROI's 64-bit seed as its two 32-bit halves, on the host: what the device programs
    make each ROI's key from (``keys``).

    Parameters
    ----------
    seeds : sequence of int
        Seeds in [0, 2**64).

    Returns
    -------
    ndarray, shape (n, 2), uint32
        The low and high halves.
    """
    seeds = np.asarray(seeds, dtype=np.uint64).reshape(-1)  # exact: never through float
    low = (seeds & np.uint64(0xFFFFFFFF)).astype(np.uint32)
    return np.stack([low, (seeds >> np.uint64(32)).astype(np.uint32)], axis=1)


def keys(words) -> object:
    """One JAX PRNG key per ROI from its seed's halves (``seed_words``; both folded in).
    Traceable: the programs make their chunk's keys inside themselves.

    Parameters
    ----------
    words : array_like, shape (n, 2), uint32
        ``seed_words`` of the seeds.

    Returns
    -------
    jax.Array
        Keys, shape (n,).
    """
    jax, jnp = jax_modules()
    words = jnp.asarray(words)

    def one(lo, hi):
        return jax.random.fold_in(jax.random.fold_in(jax.random.key(0), lo), hi)

    return jax.vmap(one)(words[:, 0], words[:, 1])


def pearson(model, counts: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``bayespsf.inference.gof.pearson`` on JAX's device, for the cameras whose count
    variance is affine in the expected photons (Photon, EMCCD); others on the host.

    Parameters
    ----------
    model : Model
        The inference model.
    counts : ndarray, shape (n, roi, roi)
        Validated ROIs in ADU.
    theta : ndarray, shape (n, 6)
        Where each ROI is judged (its maximum-likelihood fit).

    Returns
    -------
    ndarray, shape (n,)
        Pearson's statistic per ROI.
    """
    from bayespsf.inference import gof

    _, jnp = jax_modules()
    per_adu, offset = model.camera.photons_per_adu()
    v0 = float(model.camera.variance(0.0))
    v1 = float(model.camera.variance(1.0)) - v0
    affine = np.isclose(float(model.camera.variance(100.0)), v0 + 100 * v1, rtol=1e-12)
    if not (affine and np.ndim(per_adu) == 0 and np.ndim(offset) == 0) or len(counts) == 0:
        return gof.pearson(model, counts, theta)
    start_jax()
    law = jnp.asarray([float(offset), float(per_adu), v0, v1])
    (out,) = _chunked(
        _program("pearson"),
        JaxModel.from_model(model),
        [np.asarray(counts), np.asarray(theta)],
        max(1, 2**22 // model.roi**2),
        law,
    )
    return out


@functools.cache
def _program(kind: str, keep: bool = True, **static):
    """The jitted program ``kind`` of ``jax_programs`` over a chunk of ROIs, for the static
    arguments ``static``; without ``keep`` the draws (the last output of ``laplace``,
    ``gaussian`` and ``importance``) are not returned, so the device never writes them out."""
    jax, _ = jax_modules()
    function = functools.partial(getattr(jax_programs, kind), **static)
    axes = {"laplace": (None, 0, 0, 0, 0), "pearson": (None, 0, 0, None)}.get(kind)
    if axes is not None:  # one ROI's program: mapped over the chunk
        function = jax.vmap(function, in_axes=axes)
    position = KEY_ARGUMENT.get(kind)
    if position is not None:  # the chunk's keys from its seed words (``keys``)
        function = _keyed(function, position)
    if keep:
        return jax.jit(function)
    return jax.jit(lambda *args: (*function(*args)[:-1], None))


def _keyed(function, position: int):
    """``function`` taking seed words (``seed_words``) where it takes keys (argument
    ``position``)."""

    def keyed(*args):
        args = list(args)
        args[position] = keys(args[position])
        return function(*args)

    return keyed


def _scored(kind: str, keep: bool, jm, arrays: list, chunk: int, *shared, rows=None, **static):
    """``_chunked`` of a scoring program (``jax_programs``: its first output says per ROI
    whether the interpolated law passed its check) over the ROIs ``rows`` of ``arrays`` (all
    where None), then the same program with the law itself (``exact``) on the ROIs that did
    not pass; the outputs after the first."""
    usable, *results = _chunked(
        _program(kind, keep, exact=False, **static), jm, arrays, chunk, *shared, rows=rows
    )
    redo = np.flatnonzero(~usable)
    if redo.size:
        _, *again = _chunked(
            _program(kind, keep, exact=True, **static), jm, arrays, chunk, *shared,
            rows=redo if rows is None else rows[redo],
        )  # fmt: skip
        for result, value in zip(results, again, strict=True):
            if result is not None:
                result[redo] = value
    return results


def round_size(needed):
    """The Gaussian round's draws for ``needed`` draws: the smallest of ``MIN_BATCH / 2``
    times a power of ``ROUND_STEP`` (9% apart) that holds them.

    Parameters
    ----------
    needed : float or array_like
        Draws needed (per ROI).

    Returns
    -------
    int or ndarray of int
        The draws, an int for a number and an array for an array.
    """
    needed = np.maximum(np.asarray(needed, dtype=float), 1.0)
    steps = np.ceil(np.log(needed / (MIN_BATCH // 2)) / np.log(ROUND_STEP) - 1e-9)
    sizes = np.ceil((MIN_BATCH // 2) * ROUND_STEP ** np.maximum(0.0, steps)).astype(int)
    return int(sizes) if sizes.ndim == 0 else sizes


def _chunked(program, jm, arrays: list, size: int, *shared, rows=None) -> list[np.ndarray]:
    """``program(jm, *arrays)`` over the ROIs ``rows`` (indices into the host arrays' first
    axis; all where None) in chunks of ``size`` (the last padded with its first ROI), outputs
    gathered on the host. Chunks are cut on the host, each ROI's inputs copied once (a chunk
    of consecutive ROIs is a view): the device sees only the programs' own fixed shapes, never
    an operation whose shape depends on how many ROIs a stage holds, which would compile anew
    for each count. Each chunk is dispatched before the one before it is gathered, so that
    the device computes while the host waits for and copies the last chunk's outputs (JAX
    dispatches asynchronously; two chunks at most are in flight)."""
    n = len(arrays[0]) if rows is None else len(rows)
    size = bucket(n, size)
    parts, flight = [], []
    for first in range(0, n, size):
        k = min(size, n - first)
        if rows is None and k == size:
            chunk = [a[first : first + size] for a in arrays]
        else:
            take = np.full(size, first)
            take[:k] += np.arange(k)
            take = take if rows is None else rows[take]
            chunk = [a[take] for a in arrays]
        out = program(jm, *chunk, *shared)
        flight.append((out if isinstance(out, tuple) else (out,), k))
        if len(flight) == 2:
            parts.append(_gathered(*flight.pop(0)))
    parts += [_gathered(*one) for one in flight]
    return [
        None if column[0] is None else np.concatenate(column) for column in zip(*parts, strict=True)
    ]


def _gathered(outputs: tuple, k: int) -> list:
    """A chunk's outputs on the host, its first ``k`` ROIs (the rest are padding)."""
    return [None if o is None else np.asarray(o)[:k] for o in outputs]


def posteriors(stack, model, fits, seeds, settings, truths=None, keep_draws: bool = False):
    """The chain-free posteriors of a stack on JAX's device (module docstring).

    Parameters
    ----------
    stack : ndarray, shape (n, roi, roi)
        Validated ROIs in ADU.
    model : Model
        The inference model.
    fits : pandas.DataFrame
        ``fit_mle``'s rows of the stack (with the Laplace columns).
    seeds : sequence of int
        Each ROI's seed.
    settings : Settings
        ``method`` (``auto``, ``laplace`` or ``importance``) and ``ess``.
    truths : ndarray, shape (n, 6), optional
        True parameters: SBC ranks.
    keep_draws : bool
        Also return each ROI's equally weighted draws (to store them).

    Returns
    -------
    dict
        Arrays over the ROIs: ``made`` (bool: a posterior was made; else the chain is needed),
        ``method``, ``why``, ``converged``, ``ess``, ``khat``, ``weight_sd``, ``draws_scored``,
        ``draws`` (the count), ``mean``, ``sd`` (n, 6), ``quantiles`` (n, 9, 6), ``rank``
        (n, 6; -1 where none), and with ``keep_draws`` ``samples``: a list of (k, 6) arrays
        (None where none was made).
    """
    jax, _ = jax_modules()
    start_jax()
    jm = JaxModel.from_model(model)
    n = len(stack)
    platform = jax.devices()[0].platform
    budget = DRAW_PIXELS["cpu" if platform == "cpu" else "gpu"]
    ok = fits["converged"].to_numpy(bool)
    out = _empty(n, keep_draws)
    out["why"][:] = (
        "chain: the maximum-likelihood fit did not converge, so there is no Laplace proposal"
    )
    todo = np.flatnonzero(ok)
    if todo.size == 0:
        return out
    centre, cov = laplace_in_z(fits if todo.size == n else fits.iloc[todo], model)
    chol = _choleskys(cov)
    usable = np.all(np.isfinite(chol), axis=(1, 2))
    out["why"][todo[~usable]] = "chain: the Laplace covariance is not positive definite"
    if not usable.all():
        todo, centre, chol = todo[usable], centre[usable], chol[usable]
    theta = fits[["x0", "y0", "s_x", "s_y", "N", "b"]].to_numpy(float)[todo]
    fallback = np.clip(theta, *model.prior_bounds())  # inside the prior: scored in its place
    truth = np.full((n, 6), np.nan) if truths is None else np.asarray(truths, float)
    counts = np.asarray(stack, float)
    data = [counts if todo.size == n else counts[todo], centre, chol, seed_words(seeds)[todo],
            fallback, truth[todo]]  # fmt: skip  # on the host: ``_chunked``
    run = _Run(jm, out, todo, data, settings, budget, keep_draws)
    left = np.ones(len(todo), bool)
    if settings.method in ("auto", "laplace"):
        left = run.laplace()
    if settings.method in ("auto", "importance"):
        run.student_t(left)
    return out


class _Run:
    """The stages of ``posteriors`` over its ROIs ``todo`` (``data``: their counts, Laplace
    centres and Cholesky factors, keys, fallback points and truths), filling ``out``."""

    def __init__(self, jm, out, todo, data, settings, budget, keep):
        self.jm, self.out, self.todo, self.data = jm, out, todo, data
        self.settings, self.budget, self.keep = settings, budget, keep
        self.scored = np.zeros(len(todo), int)

    def _chunk(self, draws: int) -> int:
        return max(1, self.budget // (draws * self.jm.roi**2))

    def laplace(self) -> np.ndarray:
        """The pilot, the Laplace where it passes (every ROI for ``laplace``) and, for
        ``auto``, the Gaussian round; returns which ROIs are left for the Student-t."""
        out, todo, settings = self.out, self.todo, self.settings
        weight_sd, pilot_ratio = _scored("pilot", True, self.jm, self.data[:5], self._chunk(PILOT))
        out["weight_sd"][todo] = weight_sd
        self.scored[:] = PILOT
        passed = weight_sd <= LAPLACE_WEIGHT_SD
        take = passed if settings.method == "auto" else np.ones(len(todo), bool)
        out["why"][todo[~take]] = [
            f"Laplace rejected (pilot weight SD {v:.3g} > {LAPLACE_WEIGHT_SD})"
            for v in weight_sd[~take].tolist()
        ]
        wanted = CHAINS * int(np.ceil(settings.ess / CHAINS))
        if take.any():
            pick = np.flatnonzero(take)
            results = _chunked(
                _program("laplace", self.keep, wanted=wanted),
                self.jm,
                [self.data[k] for k in (1, 2, 3, 5)],
                max(1, self.budget // (2 * wanted * 6)),
                rows=None if take.all() else pick,
            )
            rows = todo[pick]
            _store(out, rows, results, self.keep)
            out["method"][rows] = "laplace"
            out["draws_scored"][rows] = PILOT
            out["ess"][rows] = results[-2]
            out["converged"][rows] = passed[pick]
            out["why"][rows] = [
                f"Laplace (pilot weight SD {v:.3g} {'<=' if p else '>'} {LAPLACE_WEIGHT_SD})"
                for v, p in zip(weight_sd[pick].tolist(), passed[pick].tolist(), strict=True)
            ]
        left = ~take
        if settings.method == "auto":
            continued = np.flatnonzero(left & (weight_sd <= GAUSSIAN_WEIGHT_SD))
            if continued.size:
                done = self.gaussian(continued, pilot_ratio)
                left[continued[done]] = False
        return left

    def gaussian(self, rows: np.ndarray, pilot_ratio: np.ndarray) -> np.ndarray:
        """The Gaussian round of the ROIs ``rows`` (positions in ``todo``), each sized from
        its pilot's raw ESS (``pilot_ratio``: the pilot's log weights, every ROI of
        ``todo``); returns which succeeded."""
        ess, limit = self.settings.ess, int(MAX_DRAWS_PER_ESS * self.settings.ess)
        ratio = pilot_ratio[rows]
        w = np.exp(ratio - ratio.max(axis=1, keepdims=True))
        raw = np.sum(w, axis=1) ** 2 / np.sum(w * w, axis=1)
        needed = GAUSSIAN_MARGIN * (ess - raw) * PILOT / np.maximum(raw, 1.0)
        most = limit - PILOT  # the run's draws stay within MAX_DRAWS_PER_ESS * ess
        sizes = np.minimum(round_size(np.maximum(needed, MIN_BATCH // 2)), most)
        done = np.zeros(len(rows), bool)
        for size in np.unique(sizes):
            group = np.flatnonzero(sizes == size)
            pick = rows[group]
            results = _scored(
                "gaussian", self.keep, self.jm, [*self.data, pilot_ratio],
                self._chunk(PILOT + int(size)), rows=pick, size=int(size),
            )  # fmt: skip
            self.scored[pick] += size
            done[group] = self._judged(pick, results, PILOT + int(size), "the Laplace Gaussian")
        return done

    def _judged(self, pick, results, draws: int, source: str, last: bool = True) -> np.ndarray:
        """Record a round of the ROIs ``pick`` (positions in ``todo``) of ``draws`` draws
        each: those whose k-hat and ESS pass are done; the others' reason is the chain's where
        this was their ``last`` chance or k-hat failed. Returns which are settled: done, and
        before the ``last`` round also those whose k-hat failed (no further round helps)."""
        out, ess_target = self.out, self.settings.ess
        khat, ess = results[-4], results[-3]
        rows = self.todo[pick]
        done = (ess >= ess_target) & (khat <= KHAT_MAX)
        failed = ~done & ((khat > KHAT_MAX) | ~np.isfinite(khat) | last)
        told = np.flatnonzero(done | failed)  # each ROI's reason, in one string
        piloted = np.isfinite(out["weight_sd"][rows[told]])  # the pilot's verdict comes first
        out["why"][rows[told]] = [
            f"{w + '; ' if prefix else ''}{'' if ok else 'chain: '}importance sampling from "
            f"{source}{'' if ok else ' failed'} (k-hat {k:.2f}, ESS {e:.0f} of {draws} draws)"
            for w, prefix, ok, k, e in zip(
                out["why"][rows[told]], piloted.tolist(), done[told].tolist(),
                khat[told].tolist(), ess[told].tolist(), strict=True,
            )
        ]  # fmt: skip
        out["khat"][rows], out["draws_scored"][rows] = khat, self.scored[pick]
        good = np.flatnonzero(done)
        _store(
            out,
            rows[good],
            [r[good] for r in results[:4]]
            + [results[-2][good], None if results[-1] is None else results[-1][good]],
            self.keep,
        )
        out["method"][rows[good]] = "importance"
        out["ess"][rows[good]] = ess[good]
        out["converged"][rows[good]] = True
        return done if last else done | failed

    def student_t(self, left: np.ndarray) -> None:
        """Student-t rounds for the ROIs ``todo[left]`` (module docstring)."""
        _, jnp = jax_modules()
        size = first_batch(self.settings.ess)
        limit = int(MAX_DRAWS_PER_ESS * self.settings.ess)
        pending = np.flatnonzero(left)
        for round_ in range(MAX_ROUNDS):
            if pending.size == 0:
                break
            results = _scored(
                "importance", self.keep, self.jm, self.data, self._chunk(size),
                jnp.asarray(round_), rows=pending, size=size,
            )  # fmt: skip
            self.scored[pending] += size
            settled = self._judged(
                pending, results, size, "the Laplace Student-t", last=round_ == MAX_ROUNDS - 1
            )
            size = min(limit, 2 * size)  # fixed sizes: the programs a dataset needs compile once
            pending = pending[~settled]


def _store(out, rows, results, keep_draws) -> None:
    """Copy a method's per-ROI summary (mean, sd, quantiles, rank, ..., count, draws)."""
    mean, sd, quantiles, rank = results[:4]
    count, draws = results[-2], results[-1]
    out["made"][rows] = True
    out["mean"][rows], out["sd"][rows] = mean, sd
    out["quantiles"][rows], out["rank"][rows] = quantiles, rank
    out["draws"][rows] = count
    if keep_draws:
        for r, d, c in zip(rows, draws, count, strict=True):
            out["samples"][r] = d[: int(c)]


def _empty(n: int, keep_draws: bool) -> dict:
    out = {
        "made": np.zeros(n, bool),
        "method": np.full(n, "mcmc", dtype=object),
        "why": np.full(n, "", dtype=object),
        "converged": np.zeros(n, bool),
        "ess": np.full(n, np.nan),
        "khat": np.full(n, np.nan),
        "weight_sd": np.full(n, np.nan),
        "draws_scored": np.zeros(n, int),
        "draws": np.zeros(n, int),
        "mean": np.full((n, 6), np.nan),
        "sd": np.full((n, 6), np.nan),
        "quantiles": np.full((n, len(QUANTILES), 6), np.nan),
        "rank": np.full((n, 6), -1),
    }
    if keep_draws:
        out["samples"] = [None] * n
    return out


__all__ = [
    "MAX_ROUNDS",
    "ROUND_STEP",
    "keys",
    "pearson",
    "posteriors",
    "round_size",
    "seed_words",
]
