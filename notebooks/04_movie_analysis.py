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
# # From a movie to per-molecule posteriors: the paper's experiment, simulated
#
# DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010) measured width precision on movies of
# immobile streptavidin-Cy3 molecules: pick molecules, keep those with one bleaching step,
# cut a 25 x 25 ROI around each, fit the central 15 x 15, apply five selection rules, and
# compare the spread of each molecule's widths over frames (its Δs) with their closed form.
# `bayespsf.analyze` does all of it on a movie, and adds what a least-squares fit cannot
# give: a posterior per frame, the joint posterior of each molecule over its frames, a check
# of the model on the data without ground truth, and a goodness-of-fit test per frame.
#
# Here the movie is the shipped `paper-movie` scene, simulated. `IMAGES` is its number of
# frames and `MOLECULES` its number of molecules (the tests use a short movie); `ESS` is the
# effective sample size of every posterior.

# %%
IMAGES = 300
MOLECULES = 40
ESS = 400
SEED = 1

# %%
import shutil
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

import bayespsf
from bayespsf.movie import Rules
from bayespsf.simulation import match_truth, simulate_movie

OUT = Path("movie-analysis")  # beside the notebook; holds the movie and every result file
shutil.rmtree(OUT, ignore_errors=True)  # made afresh: a rerun with other budgets is another run
scene = bayespsf.load_scene("paper-movie").replace(
    movie={"frames": IMAGES, "molecules": MOLECULES, "dark_frames": 0}
)
made = simulate_movie(scene, seed=SEED, out=OUT / "paper")
print(made.files["movie"], f"{IMAGES} frames, {MOLECULES} molecules")

# %% [markdown]
# ## Analyse it
#
# The camera is the simulator's own (a real movie's comes from `bayespsf calibrate`). The
# paper's rule 2 asks 75 valid frames per molecule; a short movie asks fewer.

# %%
model = bayespsf.Model.from_scene(scene)
rules = Rules(min_valid_frames=min(75, IMAGES // 3))
result = bayespsf.analyze(
    made.files["movie"],
    model,
    s0=120.0,
    out=OUT / "analysis",
    rules=rules,
    ess=ESS,
    seed=SEED,
    workers=2,
    progress=False,
)
chosen = result.molecules[result.molecules["selected"]]
print(f"{len(chosen)} molecules selected, {len(result.frames)} frames analysed")
print(sorted(p.name for p in result.paths.values()))

# %% [markdown]
# ## What the selection rules removed
#
# In order, as the paper applied them (its section "Data acquisition and selection").

# %%
print(result.found.report_markdown())

# %% [markdown]
# ## The check without ground truth
#
# An immobile molecule has one position and one width: its per-frame posterior means must
# scatter about their combined value as their stated SDs say. z-score SDs of 1 within their
# SE mean that the camera law and the PSF hold on these data. (This scene's background is a
# Gaussian truncated at zero, a little sub-Poisson where the model's is Poisson: the
# posteriors are a little wide, and the widths' z-score SDs read a little under 1.)

# %%
result.consistency[
    ["parameter", "frames", "molecules", "z_sd", "z_sd_se", "coverage", "expected_coverage"]
]

# %% [markdown]
# ## The joint posterior over frames, against the truth
#
# Each molecule's frames share x0, y0, s_x and s_y; N and b are each frame's own. The joint
# SD is about one frame's over √K. The simulator knows the truth, so we can see whether the
# joint 95% interval of s_x holds it (NaN where a selected molecule is not one immobile
# fluorophore of the simulation: the rules can let such a molecule through).

# %%
row = match_truth(chosen, made.molecules)  # -1: a selected molecule that matches none
truth = made.molecules.iloc[np.maximum(row, 0)]
one_fluorophore = (truth["fluorophores"] == 1) & ~truth["moving"].astype(bool)
joint = chosen.assign(
    s_x_truth=truth["s_x"].where((row >= 0) & one_fluorophore.to_numpy()).to_numpy()
)
joint["covers s_x"] = joint["s_x_joint_q2.5"].le(joint["s_x_truth"]) & joint["s_x_truth"].le(
    joint["s_x_joint_q97.5"]
)
joint["sd x sqrt(K) / frame sd"] = (
    joint["s_x_joint_sd"] * np.sqrt(joint["joint_frames"]) / joint["s_x_frame_sd"]
)
joint[
    [
        "molecule",
        "joint_frames",
        "s_x_joint_mean",
        "s_x_joint_sd",
        "s_x_frame_sd",
        "sd x sqrt(K) / frame sd",
        "s_x_truth",
        "covers s_x",
        "joint_method",
    ]
]

# %% [markdown]
# ## The paper's experimental Δs against N
#
# Per molecule, the SD over frames of each estimator's s_x (least squares, as the paper;
# MLE; posterior mean), beside the mean posterior SD, the Cramér-Rao bound and the paper's
# Eq. sigma2dp3 at the molecule's mean N.

# %%
spread = result.width_spread
fig, ax = plt.subplots(figsize=(6, 4))
for column, marker in (
    ("delta_s_lsq", "o"),
    ("delta_s_mle", "s"),
    ("delta_s_mean", "^"),
    ("posterior_sd", "x"),
    ("eq_sigma2dp3", "+"),
):
    ax.loglog(spread["N"], spread[column], marker, label=column)
ax.set_xlabel("mean N per frame (photons)")
ax.set_ylabel("s_x error (nm)")
ax.legend(fontsize=8)
# %% [markdown]
# ## Can the model have made each image?
#
# The goodness-of-fit p-values (`gof_p`) follow their law where the model holds: at each value
# `s` a p-value takes, the share of frames with `gof_p <= s` is `s` (the diagonal). Points
# above it at small `s` would mean ROIs the model does not describe (two molecules, a hot
# pixel, a spot that is not Gaussian). A ROI's replicates stop once 10 are as discrepant as
# it is, so above 0.2 the p-values take the values 10/l and a histogram is not flat.

# %%
p = np.sort(result.frames["gof_p"].dropna().to_numpy())
s = np.unique(p)
fig, ax = plt.subplots(figsize=(5, 3))
ax.plot([0, 1], [0, 1], "k--", lw=1, label="model holds")
ax.plot(s, np.searchsorted(p, s, side="right") / p.size, ".", ms=3, label="frames")
ax.set_xlabel("goodness-of-fit p-value s")
ax.set_ylabel("share of frames with gof_p <= s")
ax.legend(fontsize=8)
# %% [markdown]
# The same results are on disk for other tools: `locs.hdf5` + `locs.yaml` open in picasso,
# `locs.csv` in ThunderSTORM, `locs.parquet` in pandas; `report.md` has the figures.

# %%
pd.read_csv(OUT / "analysis" / "locs.csv").head()
