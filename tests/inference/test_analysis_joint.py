"""The joint posterior of an immobile molecule over its frames (bayespsf.inference.joint): the
joint log posterior against its definition, the joint fit and Laplace against the summed
information, and calibration on simulated molecules whose truth is shared by their frames."""

import numpy as np
import pytest

from bayespsf import load_scene
from bayespsf.errors import BayespsfInputError
from bayespsf.inference import fit_mle, joint_posterior
from bayespsf.inference.joint import Layout, joint_log_posterior, joint_mle
from bayespsf.inference.solver import METRIC_FLOOR, _information
from bayespsf.model import Model
from bayespsf.psf import PARAMETER_NAMES

MODEL = Model.from_scene(load_scene("emccd-typical"))
# x0, y0 in nm from the ROI's centre, s_x, s_y in nm, N and b in photons
TRUTH = np.array([12.0, -23.0, 128.0, 134.0, 1000.0, 10.0])


def frames_of(k: int, rng, truth=TRUTH, model=MODEL):
    """``k`` frames of one immobile molecule: the same position and width, the photon count
    changing from frame to frame (+-30%), as on a real trace."""
    truths = np.tile(truth, (k, 1))
    truths[:, 4] *= rng.uniform(0.7, 1.3, k)
    return model.camera.sample(model.expected(truths), rng), truths


def test_layout_round_trips_and_builds_the_arrow_matrix():
    layout = Layout(3, (0, 1, 2, 3))
    rng = np.random.default_rng(0)
    v = rng.normal(size=layout.size)
    assert layout.size == 4 + 3 * 2
    assert np.array_equal(layout.join(layout.split(v)), v)
    blocks = rng.normal(size=(3, 6, 6))
    # the joint matrix is sum_k E_k' B_k E_k, with E_k the frame's selection of the joint vector
    expected = np.zeros((layout.size, layout.size))
    for k in range(3):
        e = np.zeros((6, layout.size))
        for i, j in enumerate(layout.shared):
            e[j, i] = 1.0
        for i, j in enumerate(layout.own):
            e[j, 4 + 2 * k + i] = 1.0
        expected += e.T @ blocks[k] @ e
    assert np.allclose(layout.arrow(blocks), expected, rtol=0, atol=1e-12)
    g = rng.normal(size=(3, 6))
    assert np.allclose(layout.gather(g), sum(g[k] @ _selection(layout, k) for k in range(3)))


def _selection(layout, k):
    e = np.zeros((6, layout.size))
    e[list(layout.shared), range(len(layout.shared))] = 1.0
    own = len(layout.own)
    e[list(layout.own), range(4 + own * k, 4 + own * (k + 1))] = 1.0
    return e


def _compose(layout, shared_from, own_from):
    out = np.array(own_from, dtype=float)
    out[list(layout.shared)] = shared_from[list(layout.shared)]
    return out


# a prior whose log density and log-coordinate Jacobian do not cancel, so that counting a shared
# parameter's prior or Jacobian K times, not once, changes the differences between draws
INFORMATIVE = MODEL.__class__.from_scene(
    load_scene("emccd-typical").replace(
        prior={
            "x0": {"kind": "normal", "mean": 0.0, "sd": 30.0},
            "s_x": {"kind": "uniform", "low": 10.0, "high": 1500.0},
            "b": {"kind": "half-normal", "scale": 20.0},
        }
    )
)


@pytest.mark.parametrize("model", [MODEL, INFORMATIVE], ids=["flat", "informative"])
@pytest.mark.parametrize("shared", [(0, 1, 2, 3), (0, 1, 2, 3, 5)])
def test_joint_log_posterior_is_its_definition(shared, model):
    # sum over frames of the log-likelihood, the prior of each shared parameter once and each
    # frame's own once, and the log-coordinate Jacobian likewise: compared between draws, as
    # both sides are defined up to the same constant
    rng = np.random.default_rng(1)
    counts, truths = frames_of(4, rng)
    counts = model.check_shape(counts)
    layout = Layout(4, shared)
    z = layout.join(model.to_unconstrained(truths))[None] + rng.normal(0, 0.01, (5, layout.size))
    ours = joint_log_posterior(model, counts, layout, z, anchor=truths[0])
    # one importance run scores its draws batch by batch: the constant must not depend on the
    # batch (it once took the frames' own parameters from each batch's first draw, a change of
    # units). The scorer interpolates the law over each batch's range, so a draw's value moves
    # between batches within its tolerance (bayespsf.inference.fused; ~1e-8 here): 1e-6
    batches = [
        joint_log_posterior(model, counts, layout, z[part], anchor=truths[0])
        for part in (slice(0, 2), slice(2, 5))
    ]
    assert np.allclose(np.concatenate(batches), ours, rtol=0, atol=1e-6)
    per_frame = model.from_unconstrained(layout.split(z))  # (5, 4, 6)
    direct = np.empty(5)
    for i in range(5):
        p = per_frame[i]
        loglik = sum(float(model.log_likelihood(counts[k], p[k])) for k in range(4))
        # the prior is a product over parameters: each part scored with the others held fixed
        prior = model.log_prior(_compose(layout, p[0], truths[0])) + sum(
            model.log_prior(_compose(layout, truths[0], p[k])) for k in range(4)
        )
        jacobian = np.log(p[0, 2]) + np.log(p[0, 3]) + np.log(p[:, 4]).sum()
        direct[i] = loglik + prior + jacobian
    assert np.allclose(ours - ours[0], direct - direct[0], rtol=0, atol=1e-8)


def test_joint_fit_is_where_the_summed_gradient_vanishes():
    rng = np.random.default_rng(2)
    counts, _ = frames_of(6, rng)
    counts = MODEL.check_shape(counts)
    starts = fit_mle(counts, MODEL, laplace=False)[list(PARAMETER_NAMES)].to_numpy(float)
    layout = Layout(6, (0, 1, 2, 3))
    fit, converged, message = joint_mle(MODEL, counts, starts, layout)
    assert converged, message
    assert np.ptp(fit[:, :4], axis=0).max() == 0  # one position and width for every frame
    # a stationary point of the joint likelihood: a small step in any shared parameter lowers it
    base = MODEL.log_likelihood(counts, fit).sum()
    for k, h in zip(range(4), (0.5, 0.5, 0.5, 0.5), strict=True):
        for sign in (-1, 1):
            moved = fit.copy()
            moved[:, k] += sign * h
            assert MODEL.log_likelihood(counts, moved).sum() < base


def _joint_crlb(truths, model, layout):
    """SDs of the shared parameters from the joint expected information at the truth."""
    lam, jac = model.expected_and_jacobian(truths)
    information = _information(
        jac, model.camera.fisher_information_unchecked(np.maximum(lam, METRIC_FLOOR))
    )
    return np.sqrt(np.diag(np.linalg.inv(layout.arrow(information)))[: len(layout.shared)])


@pytest.mark.slow
def test_joint_posterior_is_calibrated_and_shrinks_as_one_over_root_k():
    # 60 molecules of K = 8 frames. Truth: the joint posterior's z-scores about the shared truth
    # have SD 1 (SE of an SD from 60 values: 1/sqrt(2 * 59) = 0.092; tolerance 0.75 to 1.3,
    # about 3 SE), and its SD matches the joint Cramér-Rao bound at the truth (posterior SD and
    # CRLB agree to O(1/N) at 1 000 photons; the SD of 400 draws has 3.5% Monte Carlo error:
    # tolerance 12%). With K frames the bound is ~1/sqrt(K) of one frame's.
    rng = np.random.default_rng(3)
    layout = Layout(8, (0, 1, 2, 3))
    z, ratios, methods = [], [], []
    for m in range(60):
        counts, truths = frames_of(8, rng)
        starts = fit_mle(counts, MODEL, laplace=False)[list(PARAMETER_NAMES)].to_numpy(float)
        post = joint_posterior(counts, MODEL, starts, seed=m, ess=400)
        row = post.row()
        methods.append(row["joint_method"])
        crlb = _joint_crlb(truths, MODEL, layout)
        for k, name in enumerate(("x0", "s_x")):
            j = (0, 2)[k]
            z.append((row[f"{name}_joint_mean"] - TRUTH[j]) / row[f"{name}_joint_sd"])
            ratios.append(row[f"{name}_joint_sd"] / crlb[j])
    z = np.array(z).reshape(60, 2)
    assert methods.count("importance") == 60
    assert 0.75 < z[:, 0].std() < 1.3 and 0.75 < z[:, 1].std() < 1.3
    assert abs(z.mean()) < 3 / np.sqrt(120)
    assert np.median(ratios) == pytest.approx(1.0, abs=0.12)
    one_frame = _joint_crlb(truths[:1], MODEL, Layout(1, (0, 1, 2, 3)))
    assert crlb[2] / one_frame[2] == pytest.approx(1 / np.sqrt(8), rel=0.25)


def test_a_background_free_molecule_is_fitted_on_the_box_edge():
    # b = 0 in every frame: the per-frame fits end on the box edge b = 0, and the joint fit
    # must converge there too (it once ran to its iteration limit). Importance sampling from a
    # Gaussian centred on b = 0 fails its k-hat here, and only (1/2)^5 of the Laplace's draws
    # have b >= 0 in all five frames: the result says so, with no summary, rather than return
    # draws outside the prior (it once returned 44% negative backgrounds)
    rng = np.random.default_rng(0)
    truth = TRUTH.copy()
    truth[4], truth[5] = 3000.0, 0.0
    counts, _ = frames_of(5, rng, truth=truth)
    fits = fit_mle(counts, MODEL)[list(PARAMETER_NAMES)].to_numpy(float)
    post = joint_posterior(counts, MODEL, fits, seed=1)
    row = post.row()
    assert post.info["mle_converged"] and row["s_x_joint_mle"] == pytest.approx(128, abs=15)
    assert row["joint_method"] == "none" and "prior's support" in row["joint_why"]
    assert np.isnan(row["s_x_joint_mean"]) and np.isnan(row["s_x_joint_sd"])


def test_bad_inputs_are_named():
    rng = np.random.default_rng(4)
    counts, truths = frames_of(3, rng)
    with pytest.raises(BayespsfInputError, match="K >= 2"):
        joint_posterior(counts[:1], MODEL, truths[:1])
    with pytest.raises(BayespsfInputError, match="starts must be finite"):
        joint_posterior(counts, MODEL, truths[:2])
    with pytest.raises(BayespsfInputError, match="starts must be finite"):
        joint_posterior(counts, MODEL, np.where(truths > 0, np.nan, truths))
    with pytest.raises(BayespsfInputError, match="shared must be one of"):
        joint_posterior(counts, MODEL, truths, shared="everything")
    with pytest.raises(BayespsfInputError, match="must be > 0"):
        joint_posterior(counts, MODEL, np.where(np.arange(6) == 2, -1.0, truths))


def test_one_background_for_all_frames_is_shared_like_the_position():
    # shared="one b": b is one number for every frame, reported like the position; its joint
    # SD is below the per-frame Laplace SD over sqrt(K) x 1.3 (the frames' b are the same here)
    rng = np.random.default_rng(5)
    counts, _ = frames_of(6, rng)
    fits = fit_mle(counts, MODEL)
    post = joint_posterior(
        counts, MODEL, fits[list(PARAMETER_NAMES)].to_numpy(float), seed=1, shared="one b"
    )
    row = post.row()
    assert row["joint_method"] == "importance" and np.ptp(post.draws[:, :, 5], axis=1).max() == 0
    assert abs(row["b_joint_mean"] - TRUTH[5]) < 4 * row["b_joint_sd"]
    assert row["b_joint_sd"] < 1.3 * fits["sd_b"].mean() / np.sqrt(6)


def test_a_molecule_that_moves_is_named_as_such_not_as_a_fit_on_the_prior_edge():
    # x0 moves 150 nm (~18 per-frame SDs) from frame to frame: no one position describes the
    # frames, the joint posterior fails, and its why says the frames' own positions disagree
    # (it once blamed "a fit on its edge, such as b = 0", with every b well inside its prior)
    rng = np.random.default_rng(0)
    truths = np.tile(TRUTH, (6, 1))
    truths[:, 4] *= rng.uniform(0.7, 1.3, 6)
    truths[:, 0] += 150.0 * (np.arange(6) - 3)
    counts = MODEL.camera.sample(MODEL.expected(truths), rng)
    fits = fit_mle(counts, MODEL)[list(PARAMETER_NAMES)].to_numpy(float)
    post = joint_posterior(counts, MODEL, fits, seed=1)
    why = post.info["why"]
    assert not post.info["converged"] and post.info["method"] == "none"
    assert "the frames' own fits disagree on the position (x0: chi-square" in why, why
    assert "the molecule moved, or the frames are not one molecule" in why
    assert "b = 0" not in why and "such as" not in why
    assert np.all(post.fit[:, 5] > 1.0)  # no background on its edge


def test_an_immobile_molecule_on_the_prior_edge_is_not_called_moving():
    # the background-free molecule above: its failure names b = 0, and no movement
    rng = np.random.default_rng(0)
    truth = TRUTH.copy()
    truth[4], truth[5] = 3000.0, 0.0
    counts, _ = frames_of(5, rng, truth=truth)
    fits = fit_mle(counts, MODEL)[list(PARAMETER_NAMES)].to_numpy(float)
    why = joint_posterior(counts, MODEL, fits, seed=1).info["why"]
    assert "the joint fit is on its edge: b = 0 in every frame" in why, why
    assert "disagree" not in why and "moved" not in why
