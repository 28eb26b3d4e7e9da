"""bayespsf's emcee sampler against the peer a user would otherwise pick: NumPyro's NUTS.

The same model is written in NumPyro (JAX, float64): the pixel-integrated Gaussian spot of
:func:`bayespsf.psf.expected_counts` (with its log-space tails), the scene's prior, and the
camera law of two likelihood tiers, 'poisson' (photon camera, or EMCCD counts converted to
photons) and 'gaussian' (the EMCCD chi-square model). NUTS samples the same coordinates as
emcee, ``x0, y0, log s_x, log s_y, log N, b``, with the log-Jacobian added, so its potential
energy is minus :meth:`bayespsf.model.Model.log_posterior` up to a constant (tested in
tests/repository/peer_checks.py) and both samplers face the same geometry.

For molecules of the `ideal` scene (Poisson likelihood) and of `emccd-typical` (gaussian tier),
spot fixed at the centre: the wall time of `sample_posterior` (ESS 400; its MLE start, burn-in
and convergence checks included; measured after one `fit_mle` of the same ROI, timed as
``MLE s``, which on a scene's first molecule includes bayespsf's one-time numba compilation)
against NUTS (one chain, 500 warm-up iterations adapting step
size and diagonal mass matrix, 2000 draws, started at the same MLE, whose time is not counted
for NUTS). NUTS's time is split into JIT compilation (first calls minus compiled calls),
warm-up and sampling, each compiled loop timed on its own (see :func:`run_nuts`); a user of
``MCMC.run`` pays the compilation on every call. ESS of s_x is arviz's bulk ESS for both
(emcee: its walkers as chains, after its burn-in and thinning), ESS/s for NUTS over sampling
alone, warm-up and sampling (the cost per molecule once compiled), and everything.
Ours is also run with ``method="importance"`` (Laplace importance sampling, PSIS; its ESS is
the smoothed weights' ESS, its draws being resampled independent draws).
``z mean s_x`` is the difference of the two posterior means over its Monte Carlo standard error
(|z| < 3 expected). Vectorized NUTS chains (``--chains``) sample slightly faster per ESS but
warm up several times slower on 2 cores, so one chain is the default.

    pip install -e ".[peer]"
    python benchmarks/peer.py            # full run, rewrites its section of README.md
    python benchmarks/peer.py --quick    # one molecule per scene, 1000 NUTS draws, prints only
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from functools import partial

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
import pandas as pd
from jax.scipy.special import erf, log_ndtr
from numpyro.distributions import constraints
from numpyro.infer import NUTS, init_to_value
from numpyro.infer.util import potential_energy

from bayespsf import load_scene, simulate
from bayespsf.cameras import EMCCD, Photon
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import fit_mle, sample_posterior
from bayespsf.model import LOG_PARAMETERS, Model
from bayespsf.psf import PARAMETER_NAMES

jax.config.update("jax_enable_x64", True)  # float64, as bayespsf; before any array is made

# NumPyro's one sample site: the vector of sampling coordinates x0, y0, log s_x, log s_y,
# log N, b (Model.to_unconstrained), flat (ImproperUniform on the reals) so that NUTS moves in
# exactly these coordinates; the prior and the Jacobian enter as a factor
SITE = "z"
CASES = (("ideal", "poisson"), ("emccd-typical", "gaussian"))
NUM_WARMUP = 500
LOG = np.array(LOG_PARAMETERS)


# --------------------------------------------------------------------------- the NumPyro model


@dataclass(frozen=True)
class PeerSpec:
    """What the NumPyro model needs of a :class:`Model`: geometry, prior arrays, camera law."""

    roi: int
    pixel_size: float
    clock_induced_charge: float
    likelihood: str  # "poisson" or "gaussian"
    photon_counting: bool  # counts are whole photons (Photon camera)
    readout: float  # readout SD in gain units (gaussian tier)
    photons_per_adu: float
    offset: float
    low: np.ndarray
    high: np.ndarray
    centre: np.ndarray
    scale: np.ndarray
    log_uniform: np.ndarray
    quadratic: np.ndarray

    @classmethod
    def from_model(cls, model: Model) -> PeerSpec:
        cam = model.camera
        if isinstance(cam, Photon):
            likelihood, readout = "poisson", 0.0
        elif isinstance(cam, EMCCD) and cam.likelihood in ("poisson", "gaussian"):
            likelihood, readout = cam.likelihood, cam.readout_in_gain_units
        else:
            raise BayespsfInputError(
                f"the NumPyro peer model has the 'poisson' and 'gaussian' tiers only, not {cam!r}"
            )
        per_adu, offset = cam.photons_per_adu()
        terms = model._prior_terms
        return cls(
            model.roi,
            model.pixel_size,
            model.clock_induced_charge,
            likelihood,
            isinstance(cam, Photon),
            float(readout),
            float(per_adu),
            float(offset),
            terms.low.copy(),
            terms.high.copy(),
            terms.centre.copy(),
            terms.scale.copy(),
            terms.log_uniform.copy(),
            terms.quadratic.copy(),
        )

    def to_photons(self, counts) -> np.ndarray:
        """Counts in ADU as photons (gain units), the data the NumPyro model scores."""
        t = (np.asarray(counts, dtype=np.float64) - self.offset) * self.photons_per_adu
        if self.likelihood == "poisson" and np.any(t < 0):
            raise BayespsfInputError("the 'poisson' tier has no support below zero photons")
        return t


def pixel_fractions(centre, width, roi: int, pixel_size: float):
    """JAX port of :func:`bayespsf.psf._pixel_fractions` (mass of a 1-D Gaussian per pixel,
    one-sided pixels as differences of upper tails in log space); every branch stays finite, so
    the gradient through ``where`` is too."""
    edges = (jnp.arange(roi + 1) - roi / 2.0) * pixel_size
    z = (edges - centre) / width
    lo, hi = z[:-1], z[1:]
    straddle = (lo < 0) & (hi > 0)
    right = lo >= 0
    near = jnp.where(straddle, 0.0, jnp.where(right, lo, -hi))
    far = jnp.where(straddle, 1.0, jnp.where(right, hi, -lo))
    log_tail_near, log_tail_far = log_ndtr(-near), log_ndtr(-far)
    one_sided = jnp.exp(log_tail_near) * -jnp.expm1(log_tail_far - log_tail_near)
    central = 0.5 * (erf(hi / np.sqrt(2.0)) - erf(lo / np.sqrt(2.0)))
    return jnp.where(straddle, central, one_sided)


def expected(p, spec: PeerSpec):
    """Expected photons per pixel ``(roi, roi)`` of parameters ``p = (x0 y0 s_x s_y N b)``."""
    px = pixel_fractions(p[0], p[2], spec.roi, spec.pixel_size)
    py = pixel_fractions(p[1], p[3], spec.roi, spec.pixel_size)
    return p[4] * py[:, None] * px[None, :] + p[5] + spec.clock_induced_charge


def log_prior_and_jacobian(z, p, spec: PeerSpec):
    """Log prior of ``p`` (the law of bayespsf's ``PriorTerms``) plus log |dp/dz|; -inf
    outside the prior's support. Also returns ``p`` clipped into the support, where the
    likelihood is evaluated (so that it and its gradient stay finite outside)."""
    inside = jnp.all((p >= spec.low) & (p <= spec.high))
    total = jnp.sum(z[LOG])  # log-Jacobian of the exp coordinates
    if spec.log_uniform.size:
        total -= jnp.sum(jnp.log(jnp.clip(p, spec.low, spec.high)[spec.log_uniform]))
    if spec.quadratic.size:
        q = spec.quadratic
        total -= 0.5 * jnp.sum(((p[q] - spec.centre[q]) / spec.scale[q]) ** 2)
    return jnp.where(inside, total, -jnp.inf), jnp.clip(p, spec.low, spec.high)


def peer_model(photons, spec: PeerSpec):
    """The NumPyro model: flat sites on the sampling coordinates, prior and Jacobian as a
    factor, the camera law as the observed site (``photons``: :meth:`PeerSpec.to_photons`;
    the EMCCD tiers' constant Jacobian of the ADU-to-photon conversion is left out)."""
    z = numpyro.sample(SITE, dist.ImproperUniform(constraints.real, (), (6,)))
    p = z.at[LOG].set(jnp.exp(z[LOG]))
    log_prior, p_safe = log_prior_and_jacobian(z, p, spec)
    numpyro.factor("log_prior", log_prior)
    lam = expected(p_safe, spec)
    if spec.likelihood == "gaussian":
        law = dist.Normal(lam, jnp.sqrt(2.0 * lam + spec.readout**2))
        numpyro.sample("photons", law.to_event(2), obs=photons)
    elif spec.photon_counting:
        numpyro.sample("photons", dist.Poisson(lam).to_event(2), obs=photons)
    else:  # EMCCD counts as photons are real: the Poisson pmf continued by gammaln
        log_pmf = dist.Poisson(lam, validate_args=False).log_prob(photons)
        numpyro.factor("photons", jnp.sum(log_pmf))


def potential(z, photons, spec: PeerSpec) -> float:
    """NumPyro's potential energy at sampling coordinates ``z`` (6,) (minus the log density)."""
    params = {SITE: jnp.asarray(z, dtype=jnp.float64)}
    return float(potential_energy(partial(peer_model, spec=spec), (photons,), {}, params))


# --------------------------------------------------------------------------- the benchmark


def _timed(fn, *args):
    """``fn(*args)`` and its wall time, waiting for JAX's asynchronous dispatch."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return out, time.perf_counter() - start


def run_nuts(photons, spec: PeerSpec, z0, seed: int, num_samples: int, chains: int) -> dict:
    """NUTS from ``z0`` (sampling coordinates) with ``chains`` vectorized chains.

    ``MCMC.run`` recompiles its loop on every call (its collection transform is a new closure
    each time), so a second run is not a compiled one; this drives the documented kernel
    interface (``NUTS.init``, ``NUTS.sample``) with two jitted loops instead, warm-up
    (adapting step size and diagonal mass matrix) and sampling. Each is called twice from the
    same initial state: the first calls include JIT compilation, the second are compiled; the
    draws of the second sampling call are returned.
    """
    kernel = NUTS(
        partial(peer_model, spec=spec),
        init_strategy=init_to_value(values={SITE: jnp.asarray(z0, dtype=jnp.float64)}),
    )
    args = (photons,)

    def warm_up(state):
        return jax.lax.fori_loop(0, NUM_WARMUP, lambda _, s: kernel.sample(s, args, {}), state)

    def sample(state):
        def step(s, _):
            s = kernel.sample(s, args, {})
            return s, (s.z[SITE], s.diverging)

        return jax.lax.scan(step, state, None, length=num_samples)

    key_init, key_first, key_second = jax.random.split(jax.random.key(seed), 3)
    start = time.perf_counter()
    initial = kernel.init(
        key_init if chains == 1 else jax.random.split(key_init, chains), NUM_WARMUP, None, args
    )
    warm_up, sample = jax.jit(warm_up), jax.jit(sample)
    state, _ = _timed(warm_up, initial._replace(rng_key=_keys(key_first, chains)))
    _timed(sample, state)
    first = time.perf_counter() - start
    state, warm_seconds = _timed(warm_up, initial._replace(rng_key=_keys(key_second, chains)))
    (_, (z, diverging)), sample_seconds = _timed(sample, state)
    z = np.asarray(z).reshape(num_samples, chains, 6)
    return {
        "compile": first - warm_seconds - sample_seconds,
        "warm-up": warm_seconds,
        "sampling": sample_seconds,
        "s_x": np.exp(z[..., 2]).T,  # (chain, draw)
        "divergences": int(np.asarray(diverging).sum()),
    }


def _keys(key, chains: int):
    return key if chains == 1 else jax.random.split(key, chains)


def run(quick: bool, chains: int = 1, cases=CASES) -> pd.DataFrame:
    """One row per molecule and case (scene, likelihood tier): costs, ESS of s_x, and the two
    posteriors of s_x."""
    molecules = 1 if quick else 3
    num_samples = (1000 if quick else 2000) // chains
    rows = []
    for name, likelihood in cases:
        scene = load_scene(name).replace(emitter={"position": "fixed"})
        model = Model.from_scene(scene, likelihood=likelihood)
        spec = PeerSpec.from_model(model)
        counts, _ = simulate(scene, molecules, seed=7)
        for k in range(molecules):
            c = model.check_counts(counts[k])
            # NUTS's start; on a scene's first molecule it includes bayespsf's one-time numba
            # compilation, which is thus left out of sample_posterior's time
            start = time.perf_counter()
            fit = fit_mle(c, model).iloc[0]
            mle_seconds = time.perf_counter() - start
            z0 = model.to_unconstrained(fit[list(PARAMETER_NAMES)].to_numpy(float))
            start = time.perf_counter()
            post = sample_posterior(c, model, seed=k, ess=400, progress=False)
            ours_seconds = time.perf_counter() - start
            ours = post.summary().loc["s_x"]
            start = time.perf_counter()
            fast = sample_posterior(c, model, seed=k, ess=400, progress=False, method="importance")
            fast_seconds = time.perf_counter() - start
            # importance draws are resampled iid draws: their ESS is the weights' ESS
            fast_ess = float(fast.info["ess"]) if "khat" in fast.info else np.nan
            nuts = run_nuts(jnp.asarray(spec.to_photons(c)), spec, z0, k, num_samples, chains)
            nuts_ess = float(az.ess(nuts["s_x"], method="bulk"))
            nuts_mean, nuts_sd = float(nuts["s_x"].mean()), float(nuts["s_x"].std(ddof=1))
            mcse = np.hypot(ours["sd"] / np.sqrt(ours["ess_bulk"]), nuts_sd / np.sqrt(nuts_ess))
            ours_rate = ours["ess_bulk"] / ours_seconds
            rates = {
                "sampling": nuts_ess / nuts["sampling"],
                "warm-up+sampling": nuts_ess / (nuts["warm-up"] + nuts["sampling"]),
                "all": nuts_ess / (nuts["compile"] + nuts["warm-up"] + nuts["sampling"]),
            }
            rows.append(
                {
                    "scene": name,
                    "likelihood": likelihood,
                    "ROI": f"{model.roi}x{model.roi}",
                    "N": scene.emitter["photons"],
                    "molecule": k,
                    "MLE s": mle_seconds,
                    "ours s": ours_seconds,
                    "ours ESS s_x": ours["ess_bulk"],
                    "ours ESS/s": ours_rate,
                    "NUTS chains x draws": f"{chains}x{num_samples}",
                    "NUTS compile s": nuts["compile"],
                    "NUTS warm-up s": nuts["warm-up"],
                    "NUTS sampling s": nuts["sampling"],
                    "NUTS ESS s_x": nuts_ess,
                    "NUTS ESS/s sampling": rates["sampling"],
                    "NUTS ESS/s warm-up+sampling": rates["warm-up+sampling"],
                    "NUTS ESS/s incl. compile": rates["all"],
                    "ours/NUTS sampling": ours_rate / rates["sampling"],
                    "ours/NUTS warm-up+sampling": ours_rate / rates["warm-up+sampling"],
                    "ours/NUTS incl. compile": ours_rate / rates["all"],
                    "importance s": fast_seconds,
                    "importance k-hat": fast.info.get("khat", np.nan),
                    "importance ESS/s": fast_ess / fast_seconds,
                    "importance/NUTS sampling": fast_ess / fast_seconds / rates["sampling"],
                    "importance/NUTS warm-up+sampling": fast_ess
                    / fast_seconds
                    / rates["warm-up+sampling"],
                    "ours mean s_x": ours["mean"],
                    "NUTS mean s_x": nuts_mean,
                    "ours sd s_x": ours["sd"],
                    "NUTS sd s_x": nuts_sd,
                    "z mean s_x": (ours["mean"] - nuts_mean) / mcse,
                    "NUTS divergences": nuts["divergences"],
                }
            )
    return pd.DataFrame(rows)


CASE = ["scene", "likelihood", "ROI", "N", "molecule"]
AGREEMENT = [
    "ours mean s_x",
    "NUTS mean s_x",
    "ours sd s_x",
    "NUTS sd s_x",
    "z mean s_x",
    "NUTS divergences",
]


def markdown(df: pd.DataFrame, command: str) -> str:
    """Two tables: the costs and ESS/s of s_x, then the agreement of the two posteriors."""
    from _report import machine

    costs = [c for c in df.columns if c not in AGREEMENT]
    return (
        f"Command: `{command}` on {machine()}, NumPyro {numpyro.__version__}, JAX "
        f"{jax.__version__} (CPU, float64).\n\n"
        + df[costs].to_markdown(index=False, floatfmt=".3g")
        + "\n\n"
        + df[CASE + AGREEMENT].to_markdown(index=False, floatfmt=".4g")
    )


def main(argv: list[str] | None = None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run, print only")
    parser.add_argument(
        "--chains",
        type=int,
        default=1,
        help="NUTS chains, vectorized (default 1; the draws are split among them)",
    )
    args = parser.parse_args(argv)
    df = run(args.quick, args.chains)
    command = "python benchmarks/peer.py" + (" --quick" if args.quick else "")
    command += f" --chains {args.chains}" if args.chains != 1 else ""
    text = markdown(df, command)
    from _report import publish

    publish("peer", text, args.quick)
    return df


if __name__ == "__main__":
    main()
