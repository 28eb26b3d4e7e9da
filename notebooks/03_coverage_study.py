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
# # Is the posterior calibrated? A small simulation-based calibration
#
# A posterior is *calibrated* when its 68% intervals contain the truth 68% of the time, over
# truths drawn from the prior. Simulation-based calibration (Talts, Betancourt, Simpson,
# Vehtari & Gelman, arXiv:1804.06788) checks the whole distribution: draw a truth from the
# prior, simulate an image, sample the posterior, and record the rank of the truth among
# posterior draws; the ranks are uniform exactly when the posterior is calibrated.
#
# Here an EMCCD without readout noise (gain 200) makes the data, and two likelihoods read it:
# the camera's exact law, and a Poisson law in photons that forgets the EM register's excess
# noise (F² = 2): its posterior is about √2 too narrow. `MOLECULES` sets the number of
# molecules per likelihood (the tests use a few; use 100+ for a real answer).

# %%
MOLECULES = 60
SEED = 5

# %%
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from scipy import stats

import bayespsf
from bayespsf.inference.summary import RANK_DRAWS, coverage
from bayespsf.model import camera_from_scene

scene = bayespsf.load_scene("emccd-typical").replace(camera={"readout_sd": 0.0})
scene = scene.replace(
    prior={
        "x0": {"kind": "uniform", "low": -50.0, "high": 50.0},
        "y0": {"kind": "uniform", "low": -50.0, "high": 50.0},
        "s_x": {"kind": "log-uniform", "low": 100.0, "high": 180.0},
        "s_y": {"kind": "log-uniform", "low": 100.0, "high": 180.0},
        "N": {"kind": "log-uniform", "low": 300.0, "high": 3000.0},
        "b": {"kind": "uniform", "low": 2.0, "high": 20.0},
    }
)

# %% [markdown]
# ## Truths from the prior, one image each from the camera's exact law

# %%
rng = np.random.default_rng(SEED)
exact = bayespsf.Model.from_scene(scene)  # the EMCCD law without readout: a closed form
truths = exact.sample_prior(MOLECULES, rng)
counts = camera_from_scene(scene).sample(exact.expected(truths), rng)
print(counts.shape)

# %% [markdown]
# ## Posteriors under both likelihoods
# `sample_many` runs the molecules on all cores; the result is one summary row per molecule,
# with the truth's rank among 99 near-independent posterior draws.

# %%
tables = {}
for tier in ("high-gain", "poisson"):  # without readout, "high-gain" is the exact law
    model = bayespsf.Model.from_scene(scene, likelihood=tier)
    tables[tier] = bayespsf.sample_many(counts, model, seed=SEED, truths=truths, ess=200)
tables["high-gain"][["molecule", "converged", "N_truth", "N_mean", "N_sd", "N_rank"]].head()

# %% [markdown]
# ## Rank histograms
# Under calibration each of the 5 bins holds a fifth of the molecules (grey: the 95% band of
# one bin). A posterior that is too narrow piles the ranks into the end bins (a "U").

# %%
bins = 5
low, high = stats.binom(MOLECULES, 1 / bins).ppf([0.025, 0.975])
fig, axes = plt.subplots(2, 6, figsize=(13, 4), sharey=True)
for i, (tier, table) in enumerate(tables.items()):
    for j, name in enumerate(bayespsf.PARAMETER_NAMES):
        ax = axes[i, j]
        ax.axhspan(low, high, color="0.85")
        ax.hist(table[f"{name}_rank"], bins=bins, range=(0, RANK_DRAWS + 1))
        ax.set_title(f"{name} ({tier})", fontsize=8)
fig.tight_layout()

# %% [markdown]
# ## Interval coverage
# The fraction of central intervals that hold the truth, with its binomial SE. For the
# Poisson likelihood the expected coverage follows from its √2-too-narrow posterior: a central
# interval of nominal level p covers P(|Z| < z_p / √2).

# %%
rows = []
for tier, table in tables.items():
    for p in (0.5, 0.68, 0.9, 0.95):
        c = coverage(table, p).set_index("parameter")
        rows.append(
            {
                "likelihood": tier,
                "nominal": p,
                **c["coverage"].round(2).to_dict(),
                "SE": round(float(np.sqrt(p * (1 - p) / MOLECULES)), 2),
            }
        )
result = pd.DataFrame(rows)
narrow = 2 * stats.norm.cdf(stats.norm.ppf(0.5 + result["nominal"] / 2) / np.sqrt(2)) - 1
result["expected if √2 too narrow"] = np.where(result["likelihood"] == "poisson", narrow, np.nan)
result.round(2)

# %% [markdown]
# The exact law's coverage should sit within about two SEs of nominal; the Poisson law's
# falls towards the last column for N, whose information the excess noise halves (and by a
# smaller amount for the other parameters). `validation/posterior_coverage.py` runs this study
# for every camera and likelihood tier with 100 molecules each; its results are in
# `validation/README.md`.
