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
# # Axial position: a calibrated posterior of z from the spot's widths
#
# A spot's widths change with the emitter's distance z from the focal plane. DeSantis,
# DeCenzo, Li & Wang, Opt. Express 18 (2010), Discussion, turn their width precision Δs into
# a precision of z with the symmetric defocus curve s(z) = s0 √(1 + (z / D)²), D ≈ 400 nm:
# there z and -z give the same image, and in focus the width does not change with z at all.
# Huang, Wang, Bates & Zhuang, Science 319 (2008) break the symmetry with a cylindrical lens:
# x and y come into focus at different planes, s_x and s_y change in opposite directions
# through focus, and z has one answer. Their curve per axis is
# w(z) = w0 √(1 + u² + A u³ + B u⁴), u = (z - c) / d.
#
# This notebook calibrates those curves on a simulated bead z-stack, computes the posterior
# of each molecule's z under the calibrated curves (`bayespsf.axial.posterior.z_posterior`),
# compares its spread with the Cramér–Rao bound of z, shows why a first-order error of z fails
# for the symmetric curve, and pushes a six-parameter posterior's widths through the
# calibration as a cheaper alternative. `IMAGES` is the number of frames of the z-stack,
# `MOLECULES` the number of molecules whose z is inferred (the tests use few of both), and
# `ESS` the effective sample size of every posterior.

# %%
IMAGES = 290
MOLECULES = 40
ESS = 400
SEED = 1

# %%
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

import bayespsf
from bayespsf import Model, load_scene, theory
from bayespsf.axial import calibrate, crlb_z, first_order_z_sd, step_widths, z_draws, z_posterior
from bayespsf.io import read_z_calibration, write_z_calibration
from bayespsf.psf import Defocus
from bayespsf.simulation import simulate_zstack, zstack_positions

# %% [markdown]
# ## The astigmatic scene
#
# The shipped `astigmatic` scene declares an `[axial]` table: Huang curves without the
# higher-order terms, x in focus at z = -200 nm and y at +200 nm, depth of focus 400 nm, in
# focus s0 = 130 nm on both axes; each simulated molecule draws its z uniformly in
# [-600, 600] nm. The camera, background and pixels are those of `emccd-typical`, the spot has
# 2000 photons.

# %%
scene = load_scene("astigmatic")
model = Model.from_scene(scene)
truth_defocus = Defocus.from_table(scene.axial, 130.0, 130.0)
Z_RANGE = (scene.axial["z_low"], scene.axial["z_high"])  # the scene's z law: the prior of z
print(dict(scene.axial))

z_plot = np.linspace(-800.0, 800.0, 321)
s_x, s_y = truth_defocus.widths(z_plot)
fig, ax = plt.subplots(figsize=(6, 3.8))
ax.plot(z_plot, s_x, label="s_x(z)")
ax.plot(z_plot, s_y, label="s_y(z)")
ax.axvspan(*Z_RANGE, color="grey", alpha=0.15, label="the scene's z range")
ax.set_xlabel("z (nm)")
ax.set_ylabel("width (nm)")
ax.legend(fontsize=8)
fig.tight_layout()

# %% [markdown]
# ## Calibration from a bead z-stack
#
# A bright, immobile bead (20 000 photons, at the ROI's centre) is imaged at 29 stage positions
# 50 nm apart from -700 nm, several frames per step. The frames of one step share the bead's
# position and widths, so each step's widths are the joint posterior over its frames
# (`step_widths`); per axis, `calibrate` fits the Huang curve to them by weighted least squares
# (`higher_order=False` holds A = B = 0, as this scene's curves are) and tests the fit by its
# chi-square.

# %%
STEPS = 29
FRAMES_PER_STEP = max(1, IMAGES // STEPS)
bead = scene.replace(emitter={"photons": 20000.0, "position": "fixed"})
z_stack = zstack_positions(-700.0, 50.0, STEPS, FRAMES_PER_STEP)
stack, stack_truth = simulate_zstack(bead, z_stack, SEED)
steps = step_widths(stack, z_stack, Model.from_scene(bead), seed=SEED, ess=ESS, workers=1)
cal = calibrate(
    steps,
    "huang",
    higher_order=False,
    source={
        "stack": "simulated",
        "scene": "astigmatic",
        "bead_photons": 20000.0,
        "frames_per_step": FRAMES_PER_STEP,
        "seed": SEED,
    },
)
print(f"{len(z_stack)} frames, {STEPS} steps of {FRAMES_PER_STEP}")
steps.head()

# %% [markdown]
# The fitted terms with their SDs (from the Gauss–Newton covariance), and the chi-square of
# each fit on its degrees of freedom; `problems` names any axis whose curve does not fit its
# stack (an empty list: both fit). The true terms are w0 = 130, c = ∓200, d = 400.

# %%
print("problems:", cal.problems)
cal.fits[["w0", "w0_sd", "c", "c_sd", "d", "d_sd", "chi2", "dof", "p"]]

# %%
fig, (ax, res) = plt.subplots(2, 1, figsize=(6, 5.5), sharex=True, height_ratios=(3, 1))
z_fit = np.linspace(-750.0, 750.0, 301)
for axis, color in (("x", "C0"), ("y", "C1")):
    curve = getattr(cal.defocus, axis)
    ax.errorbar(
        steps["z"],
        steps[f"s_{axis}"],
        steps[f"s_{axis}_sd"],
        fmt="o",
        ms=3,
        color=color,
        label=f"step s_{axis}",
    )
    ax.plot(z_fit, curve.width(z_fit), color=color, label=f"fitted s_{axis}(z)")
    ax.plot(z_fit, getattr(truth_defocus, axis).width(z_fit), ":", color="k", lw=0.8)
    normalised = (steps[f"s_{axis}"] - curve.width(steps["z"])) / steps[f"s_{axis}_sd"]
    res.plot(steps["z"], normalised, "o", ms=3, color=color)
ax.set_ylabel("width (nm)")
ax.legend(fontsize=8, title="dotted: the true curves", title_fontsize=8)
res.axhline(0.0, color="grey", lw=0.8)
res.set_xlabel("stage z (nm)")
res.set_ylabel("residual / SD")
fig.tight_layout()

# %% [markdown]
# A calibration is a TOML file (`write_z_calibration`, `read_z_calibration`): the curve, each
# axis's terms, covariance and fit, the steps it was fitted to, and the source. Here it goes
# to a temporary folder; the loaded calibration has the same curves and adds the file it came
# from to its source.

# %%
with tempfile.TemporaryDirectory() as folder:
    path = write_z_calibration(cal, Path(folder) / "astigmatic-z.toml")
    print("\n".join(path.read_text().splitlines()[:12]), "\n...")
    loaded = read_z_calibration(path)
print("same curves:", loaded.defocus == cal.defocus)
pd.Series(loaded.source, name="source")

# %% [markdown]
# ## The posterior of each molecule's z
#
# `z_posterior` samples `(x0, y0, z, N, b)` of one ROI, with the widths the calibration's
# `(s_x(z), s_y(z))` and z uniform on `z_range` (here the scene's own range, so that the
# posterior's prior is the law the molecules were drawn from). It grids z first, so every mode
# is found by construction, and then importance-samples the exact posterior; `info["khat"]`
# checks the weights (≤ 0.7 passes) and `info["calibration"]` records the calibration used.

# %%
counts, truth = bayespsf.simulate(scene, MOLECULES, SEED)
posts = [
    z_posterior(counts[k], model, cal, z_range=Z_RANGE, seed=k, ess=ESS) for k in range(MOLECULES)
]
print(f"true z of molecule 0: {truth['z'].iloc[0]:.1f} nm")
posts[0].summary()

# %%
{key: value for key, value in posts[0].info.items() if key != "calibration"}

# %%
posts[0].info["calibration"]

# %% [markdown]
# Every molecule: the posterior mean and 95% central interval of z against the truth. If the
# posterior is calibrated, each interval holds the true z with probability 0.95, so the count
# of intervals that do is binomial(`MOLECULES`, 0.95).

# %%
rows = []
for k, post in enumerate(posts):
    z = post.draws["z"]
    rows.append(
        {
            "true z": truth["z"].iloc[k],
            "mean": z.mean(),
            "sd": z.std(),
            "q2.5": z.quantile(0.025),
            "q97.5": z.quantile(0.975),
            "khat": post.info["khat"],
            "converged": post.info["converged"],
        }
    )
zs = pd.DataFrame(rows)
zs["covers"] = zs["q2.5"].le(zs["true z"]) & zs["true z"].le(zs["q97.5"])
expected, spread = 0.95 * MOLECULES, np.sqrt(0.95 * 0.05 * MOLECULES)
print(
    f"{zs['covers'].sum()} of {MOLECULES} 95% intervals hold the true z "
    f"(expected {expected:.1f} ± {spread:.1f}); {zs['converged'].sum()} posteriors passed "
    "their k-hat and ESS checks"
)

fig, ax = plt.subplots(figsize=(5, 5))
ax.errorbar(
    zs["true z"],
    zs["mean"],
    [zs["mean"] - zs["q2.5"], zs["q97.5"] - zs["mean"]],
    fmt="o",
    ms=3,
    label="posterior mean, 95% interval",
)
missed = zs[~zs["covers"]]
ax.plot(missed["true z"], missed["mean"], "rx", ms=8, label="interval misses the truth")
ax.plot(Z_RANGE, Z_RANGE, "k:", lw=0.8)
ax.set_xlabel("true z (nm)")
ax.set_ylabel("z (nm)")
ax.legend(fontsize=8)
zs.head(10)

# %% [markdown]
# The calibration is itself an estimate. `calibration_uncertainty=True` integrates z's
# posterior over the curves' terms as well (drawn from their Gaussian, `cal.covariance`). A
# bright bead pins the curves to about a nanometre, far below z's SD, so here the two differ
# by little more than their Monte Carlo noise.

# %%
wider = z_posterior(
    counts[0], model, cal, z_range=Z_RANGE, seed=0, ess=ESS, calibration_uncertainty=True
)
both_ways = {"fitted curves": posts[0], "curves' uncertainty marginalised": wider}
pd.DataFrame({name: post.summary().loc["z"] for name, post in both_ways.items()}).transpose()

# %% [markdown]
# ## Against the Cramér–Rao bound of z
#
# With the widths following z, the model has five parameters `(x0, y0, z, N, b)`; the Fisher
# information of z follows from the six-parameter one by the chain rule (`crlb_z`, which
# returns the square root of each bound, in nm). No unbiased estimator of z has a smaller SD.
# Propagating the widths' own Cramér–Rao covariance S through the curves to first order,
# 1 / √(g' S⁻¹ g) with g = (ds_x/dz, ds_y/dz) (`first_order_z_sd`), gives exactly the same
# number, as the first rows below show.

# %%
photons, background = scene.emitter["photons"], scene.background["mean"]


def sqrt_crlb_z(defocus, z, x0=0.0, y0=0.0):
    return crlb_z(model, defocus, np.array([x0, y0, z, photons, background]))["z"]


def first_order_at_crlb(defocus, z):
    """First-order SD of z with S the widths' Cramér–Rao covariance (six parameters free)."""
    s_x, s_y = defocus.widths(z)
    params = np.array([0.0, 0.0, float(s_x), float(s_y), photons, background])
    widths_cov = np.linalg.inv(theory.fisher_matrix(model, params))[2:4, 2:4]
    return float(first_order_z_sd(defocus, z, widths_cov))


pd.DataFrame(
    [
        {
            "z": z,
            "sqrt CRLB_z": sqrt_crlb_z(truth_defocus, z),
            "first order, S = widths' CRLB": first_order_at_crlb(truth_defocus, z),
        }
        for z in (-600.0, -200.0, 0.0, 300.0)
    ]
)

# %% [markdown]
# The bound against z (at the ROI's centre, the scene's N and background), beside each
# molecule's posterior SD at its true z. The bound is smallest at z = 0, midway between the
# focal planes, where both widths change with z; it has a bump near each focal plane, where
# that axis's width is stationary and only the other one informs z; and it grows towards the
# ends of the range, where the spot spreads its photons over more pixels. The posterior SDs
# scatter about the bound (one ROI's SD is itself noisy); their ratio to the bound at each
# molecule's own true parameters summarises it.

# %%
z_grid = np.linspace(*Z_RANGE, 61)
bound = np.array([sqrt_crlb_z(truth_defocus, z) for z in z_grid])
zs["sqrt CRLB_z"] = [
    crlb_z(model, truth_defocus, truth.loc[k, ["x0", "y0", "z", "N", "b"]].to_numpy(float))["z"]
    for k in range(MOLECULES)
]
ratio = zs["sd"] / zs["sqrt CRLB_z"]
print(
    f"posterior SD / sqrt CRLB_z: mean {ratio.mean():.2f}, "
    f"from {ratio.min():.2f} to {ratio.max():.2f}"
)

fig, ax = plt.subplots(figsize=(6, 3.8))
ax.plot(z_grid, bound, "k-", label="sqrt CRLB_z")
ax.plot(zs["true z"], zs["sd"], "o", ms=4, label="posterior SD of z")
ax.set_xlabel("z (nm)")
ax.set_ylabel("SD of z (nm)")
ax.set_ylim(0, None)
ax.legend(fontsize=8)
fig.tight_layout()

# %% [markdown]
# ## The paper's symmetric defocus: two answers
#
# Without the cylindrical lens both axes follow the paper's s(z) = s0 √(1 + (z / D)²), in focus
# at z = 0 (`Defocus.symmetric(130.0, 400.0)`; the `emccd-typical` scene with an `[axial]`
# table of the default symmetric curve is the same thing). A molecule at z = +250 nm makes the
# same image as one at -250 nm, so with z uniform on (-600, 600) its posterior has two mirror
# modes of equal height; `info["above_plane"]` is the posterior probability of z > 0. A
# second molecule in focus (z = 0) shows the other failure: the widths change with z only to
# second order there, so its posterior is one broad mode across focus.

# %%
symmetric = Defocus.symmetric(130.0, 400.0)
flat = load_scene("emccd-typical").replace(axial={"z": "fixed", "z0": 250.0})
flat_model = Model.from_scene(flat)
print(
    "same curves as the scene's:",
    Defocus.from_table(flat.axial, flat.emitter["s0x"], flat.emitter["s0y"]) == symmetric,
)
mirrored = {}
for z0 in (250.0, 0.0):
    roi, _ = bayespsf.simulate(flat.replace(axial={"z0": z0}), 1, SEED)
    mirrored[z0] = z_posterior(
        roi[0], flat_model, symmetric, z_range=(-600.0, 600.0), seed=SEED, ess=ESS
    )
    print(
        f"true z = {z0:g} nm: P(z > 0) = {mirrored[z0].info['above_plane']:.2f}, "
        f"k-hat {mirrored[z0].info['khat']:.2f}"
    )

fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), sharey=True)
for ax, (z0, post) in zip(axes, mirrored.items(), strict=True):
    ax.hist(post.draws["z"], bins=60, range=(-600, 600), density=True)
    for mark in {z0, -z0}:
        ax.axvline(mark, color="r", ls=":", lw=1)
    ax.set_title(f"true z = {z0:g} nm (dotted: ±z)", fontsize=9)
    ax.set_xlabel("z (nm)")
axes[0].set_ylabel("posterior density")
mirrored[250.0].summary().loc[["z"]]

# %% [markdown]
# The summary's mean and SD describe neither mode: the mean sits between them, near 0, where
# the posterior has no mass. A first-order error, z ± SD from the slopes of the curve at an
# estimate, is one Gaussian and cannot describe two modes: it can report only one of them,
# with an interval that misses the other. In focus it fails outright: the slopes vanish at
# z = 0, so the Fisher information on z is zero and both the Cramér–Rao bound and the
# first-order SD are infinite there (and huge nearby), while the in-focus molecule's
# posterior above is proper, with a finite SD (the dashed line).

# %%
widths_cov = np.diag([5.0, 5.0]) ** 2  # any width covariance: the slopes are what vanish
flat_photons, flat_background = flat.emitter["photons"], flat.background["mean"]


def flat_crlb_z(z):
    theta = np.array([0.0, 0.0, z, flat_photons, flat_background])
    return crlb_z(flat_model, symmetric, theta)["z"]


print("sqrt CRLB_z at z = 0:", flat_crlb_z(0.0))
print("first-order SD at z = 0:", first_order_z_sd(symmetric, 0.0, widths_cov))
near = np.geomspace(2.0, 600.0, 40)
flat_bound = [flat_crlb_z(z) for z in near]
fig, ax = plt.subplots(figsize=(6, 3.5))
for side in (1, -1):  # the bound is even in z; infinite at z = 0 itself
    ax.semilogy(side * near, flat_bound, "k-", label="sqrt CRLB_z" if side > 0 else None)
in_focus_sd = mirrored[0.0].draws["z"].std()
ax.axhline(in_focus_sd, color="C0", ls="--", label="posterior SD, the molecule in focus")
ax.set_xlabel("z (nm)")
ax.set_ylabel("SD of z (nm)")
ax.set_title(f"symmetric curve, N = {flat_photons:g}: the bound diverges in focus", fontsize=9)
ax.legend(fontsize=8)
fig.tight_layout()

# %% [markdown]
# ## The cheap alternative: push the widths' posterior through the curves
#
# Where a six-parameter posterior `(x0, y0, s_x, s_y, N, b)` of the ROI exists already (from
# `bayespsf.sample_posterior`, `sample_many` or `bayespsf.analyze`), `z_draws` maps each draw
# of (s_x, s_y) to the z whose calibrated widths are nearest in the metric of the draws' own
# covariance: no new sampling. It is a projection, not z's posterior: the widths' prior is
# log-uniform and free, not tied to a z law; the spread of the draws off the curve is
# discarded; and on the symmetric curve each draw is given one of its two mirror values at
# random. Near the curve its spread follows the first-order error. For this molecule, well
# inside the range at 2000 photons, the two are close; they part where the widths' posterior
# is far from Gaussian (few photons, the ends of the range), which `validation/axial.py`
# measures by coverage.

# %%
k = 0
six = bayespsf.sample_posterior(counts[k], model, seed=SEED, ess=ESS, method="auto")
widths = six.draws()  # a method here; ZPosterior.draws is a DataFrame attribute
pushed = z_draws(
    cal.defocus,
    widths["s_x"].to_numpy(),
    widths["s_y"].to_numpy(),
    np.random.default_rng(SEED),
    Z_RANGE,
)
cov = np.cov(widths[["s_x", "s_y"]].to_numpy().T)
print(
    f"six-parameter posterior: {six.method}, {len(widths)} draws; true z "
    f"{truth['z'].iloc[k]:.1f} nm; first-order SD at the pushed median "
    f"{float(first_order_z_sd(cal.defocus, np.median(pushed), cov)):.1f} nm"
)

fig, ax = plt.subplots(figsize=(6, 3.5))
both = np.concatenate([pushed, posts[k].draws["z"]])
bins = np.linspace(both.min(), both.max(), 40)
ax.hist(posts[k].draws["z"], bins=bins, density=True, alpha=0.6, label="z_posterior")
ax.hist(pushed, bins=bins, density=True, alpha=0.6, label="pushed six-parameter draws")
ax.axvline(truth["z"].iloc[k], color="k", ls=":", label="true z")
ax.set_xlabel("z (nm)")
ax.legend(fontsize=8)
fig.tight_layout()
quantiles = [0.025, 0.16, 0.5, 0.84, 0.975]
pd.DataFrame(
    {
        "z_posterior": posts[k].draws["z"].describe(percentiles=quantiles),
        "pushed": pd.Series(pushed).describe(percentiles=quantiles),
    }
).transpose()
