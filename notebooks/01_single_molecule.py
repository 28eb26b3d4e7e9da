# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # The posterior of one molecule
#
# One molecule on a typical EMCCD (gain 200, readout 50 e⁻), 300 nm above focus, so that its
# spot is wider than the in-focus width s0 = 130 nm. We sample the full posterior of
# (x0, y0, s_x, s_y, N, b), read the sampler's diagnostics, compare the posterior SD of the width
# with the paper's closed form (Eq. sigma2dp3), its pixel sum (Eq. pesum) and the Cramér–Rao
# bound, and turn the width's uncertainty into an axial one with the Discussion's formula
# (DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010)).
#
# `ESS` sets the effective sample size the sampler must reach on every parameter; the tests run
# this notebook with a small value.

# %%
ESS = 400
SEED = 3

# %%
import numpy as np

import bayespsf
from bayespsf import theory

S0, DEPTH, Z = 130.0, 400.0, 300.0  # in-focus width, imaging depth D, height above focus (nm)
s_z = float(theory.axial_width(Z, S0, DEPTH))  # the Discussion's s(z) = s0 sqrt(1 + z²/D²)
scene = bayespsf.load_scene("emccd-typical").replace(emitter={"s0x": s_z, "s0y": s_z})
print(f"width at z = {Z:g} nm: {s_z:.1f} nm")
print(bayespsf.simulation.pipeline.describe(scene))  # exactly the effects the scene declares

# %% [markdown]
# ## Simulate, then sample
# `Model.from_scene` takes the scene's camera law (for an EMCCD the `table` tier: the exact
# law, interpolated to within 1e-4 in log p) and its prior. To analyse your own data, load a
# ROI with `bayespsf.io.read_rois` instead of simulating it.

# %%
counts, truth = bayespsf.simulate(scene, n=1, seed=SEED)
true = truth.iloc[0][list(bayespsf.PARAMETER_NAMES)].to_numpy(float)
model = bayespsf.Model.from_scene(scene)
post = bayespsf.sample_posterior(counts[0], model, seed=SEED, ess=ESS, truth=true, scene=scene)
post.summary()

# %% [markdown]
# ## Diagnostics
# The run stops when every parameter's integrated autocorrelation time τ is stable, the chain
# is at least 50 τ long and the ESS target is met; `converged` says whether that happened
# before the step cap. Walkers are not independent chains, so `r_hat` over walkers is only a
# heuristic; τ and the τ-based ESS are the stronger checks.

# %%
info = post.info
print(
    f"converged: {post.converged}; {info['steps']} steps x {info['walkers']} walkers; "
    f"burn-in {info['burn']}, thinned by {info['thin']}; acceptance {info['acceptance']:.2f}"
)
print("tau (steps):", post.tau.round(1).to_dict())
assert post.converged

# %%
post.trace()
# %%
post.corner()
# %% [markdown]
# ## The width's precision: posterior against theory
# The closed form and the pixel sum assume the paper's variance per pixel,
# σᵢ² = 2Nᵢ + σb² + ⟨b⟩ (an EMCCD's excess noise factor F² = 2); for this scene's Poisson
# background σb² = ⟨b⟩. The CRLB uses the exact camera law and all six parameters free.

# %%
g, bg = scene.geometry, scene.background
args = (true[4], s_z, s_z, g["pixel_size"], np.sqrt(bg["mean"]), bg["mean"])
closed = float(theory.delta_s_analytic(*args))
pixel_sum = float(theory.delta_s_numeric(*args, roi=g["roi"]))
bound = float(theory.crlb(scene, params=true)["s_x"])
sd = float(post.sd()["s_x"])
print(f"posterior SD of s_x   {sd:6.2f} nm")
print(f"Eq. sigma2dp3         {closed:6.2f} nm  (posterior / closed form = {sd / closed:.2f})")
print(f"pixel sum (Eq. pesum) {pixel_sum:6.2f} nm")
print(f"CRLB                  {bound:6.2f} nm  (posterior / CRLB = {sd / bound:.2f})")

# %% [markdown]
# One molecule's posterior SD scatters around its expected value (the CRLB at high N); the
# validation studies (`validation/README.md`) average over many molecules.
#
# ## From width to height
# Error propagation through s(z) = s0 √(1 + z²/D²) gives Δz = D Δs / (s0 √(1 − s0²/s(z)²)):
# near focus the width is insensitive to z, and Δz grows without bound. The posterior gives
# Δz directly too: transform every draw of s_x to z and take the SD.

# %%
dz = float(theory.delta_z(sd, S0, s_z, DEPTH))
draws = post.draws()["s_x"].to_numpy()
z_draws = DEPTH * np.sqrt(np.clip(draws**2 / S0**2 - 1.0, 0.0, None))  # z >= 0: above focus
print(
    f"Δz by error propagation: {dz:.0f} nm; SD of z over the posterior draws: "
    f"{z_draws.std():.0f} nm (true z = {Z:g} nm, posterior mean {z_draws.mean():.0f} nm)"
)
