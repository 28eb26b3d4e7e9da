"""The JAX model (bayespsf.inference.jax_model) against the NumPy model it translates: expected
counts, per-pixel and summed log-likelihoods of every supported camera law at simulated and
hand-picked hard points, the prior, the Fisher information and gradients; the one documented
difference (the table tier off its grids) measured and bounded; unsupported laws refused."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bayespsf import Model, load_scene, simulate
from bayespsf.cameras import EMCCD, Photon
from bayespsf.cameras import _emccd_table as table
from bayespsf.errors import BayespsfInputError
from bayespsf.inference.jax_model import (
    SUPPORTED,
    TABLES_KEPT,
    JaxModel,
    enable_x64,
    on_device,
    release_tables,
)

SCENES = ["ideal", "emccd-typical", "paper-fig3"]  # Photon, EMCCD table (r = 0.25), no readout
TYPICAL = dict(gain=200.0, readout_sd=50.0, offset=100.0, e_per_adu=12.0)  # emccd-typical
LAMS = np.array(
    [0.0, 1e-300, 1e-12, 1e-9, 5e-7, 1e-6, 1e-6 * (1 + 1e-12), 1e-3, 0.3, 1.0, 10.0, 100.0,
     1e4, 99999.0, 1e5, 1e7]
)  # fmt: skip
STEPS = np.array([-1e4, -100, -13, -3, -1e-3, 0, 1e-3, 0.5, 3, 7, 30, 100, 1e3, 1e4, 1e6, 1e8])


# The model goes to jit as an argument (a pytree): one compiled program per law and shape.
@jax.jit
def expected(jm, p):
    return jm.expected(p)


@jax.jit
def pixel_ll(jm, counts, lam):
    return jm.pixel_log_likelihood(counts, lam)


@jax.jit
def log_likelihood(jm, counts, p):
    return jm.log_likelihood(counts, p)


@jax.jit
def log_prior(jm, p):
    return jm.log_prior(p)


@jax.jit
def fisher(jm, lam):
    return jm.fisher(lam)


@jax.jit
def value_and_gradient(jm, counts, p):
    """Each ROI's log-likelihood (n,) and its gradient by p (n, 6)."""
    return jax.vmap(jax.value_and_grad(jm.log_likelihood, argnums=1))(counts, p)


@jax.jit
def pixel_derivatives(jm, counts, lam):
    """Per pixel: log p and its first and second derivatives by lam."""

    def one(c, m):
        return jm.pixel_log_likelihood(c, m)

    first = jax.grad(one, argnums=1)
    second = jax.grad(first, argnums=1)
    return tuple(jax.vmap(f)(counts, lam) for f in (one, first, second))


def close(a, b, atol, rtol=1e-14):
    """Equal where both are the same infinity, else within ``atol + rtol |a|``: the JAX and
    NumPy special functions (log, exp, i1e, log_ndtr) round differently in the last bit, which
    is 1e-16 relative to log p, i.e. above 1e-9 absolute where |log p| exceeds ~1e7."""
    a, b = np.asarray(a), np.asarray(b)
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    with np.errstate(invalid="ignore"):
        err = np.where(same, 0.0, np.abs(a - b))
    scale = np.where(np.isfinite(a), np.abs(a), 0.0)
    return bool(np.all(err <= atol + rtol * scale))


@pytest.fixture(scope="module")
def scenes():
    out = {}
    for name in SCENES:
        scene = load_scene(name)
        model = Model.from_scene(scene)
        counts, truth = simulate(scene, 6, seed=11)
        out[name] = (model, JaxModel.from_model(model), counts, truth.to_numpy())
    return out


def grid_points(camera):
    """Counts from far below the offset to far above (in readout SDs, or gain steps without
    readout) against LAMS, flattened."""
    unit = camera.readout_sd if camera.readout_sd > 0 else camera.gain
    counts = camera.offset + STEPS * unit / camera.e_per_adu
    c, lam = np.meshgrid(counts, LAMS, indexing="ij")
    return c.ravel(), lam.ravel()


# ---------------------------------------------------------------------------- the spot


@pytest.mark.parametrize("pixel_model", ["integrated", "sampled"])
def test_expected_counts_equal_the_numpy_model_far_tails_included(pixel_model):
    # 1e-12 relative: the same formulas; only last-bit rounding of erf/log_ndtr/exp differs.
    # Without background or CIC, pixels up to ~50 widths from a narrow spot hold ~1e-500 to
    # 1e-10 of it; wherever the NumPy value is a normal double it is matched to 1e-12 relative.
    rng = np.random.default_rng(1)
    draws = np.column_stack(
        [rng.uniform(-300, 300, (40, 2)), rng.uniform(60, 300, (40, 2)),
         10 ** rng.uniform(1, 5, 40), rng.uniform(0, 20, 40)]
    )  # fmt: skip
    tails = np.array(
        [[0.0, 0.0, 30.0, 30.0, 1e4, 0.0], [690.0, -640.0, 15.0, 40.0, 1e3, 0.0],
         [-37.0, 12.0, 100.0, 25.0, 1.0, 0.0], [400.0, 400.0, 12.0, 12.0, 5e3, 0.0]]
    )  # fmt: skip
    p = np.concatenate([draws, tails])
    with_qe = Model(15, 100.0, Photon(), None, 0.05, 0.0, pixel_model, 0.8, "incident")
    got = np.asarray(expected(JaxModel.from_model(with_qe), p))
    np.testing.assert_allclose(got, with_qe.expected(p), rtol=1e-12, atol=0)
    plain = Model(15, 100.0, Photon(), pixel_model=pixel_model)
    want = plain.expected(p)
    got = np.asarray(expected(JaxModel.from_model(plain), p))
    normal = want > 1e-290
    assert want[normal].min() < 1e-200 and (~normal).any()  # the far tails are compared
    np.testing.assert_allclose(got[normal], want[normal], rtol=1e-12, atol=0)
    assert np.all(got[~normal] < 1e-280)


# ---------------------------------------------------------------------------- camera laws


CAMERAS = {
    **{f"readout-{t}": EMCCD(**TYPICAL, likelihood=t) for t in ("poisson", "gaussian")},
    "readout-high-gain": EMCCD(**TYPICAL, likelihood="high-gain"),
    **{
        f"no-readout-{t}": EMCCD(200.0, 0.0, 100.0, 12.0, t)
        for t in ("exact", "table", "high-gain", "gaussian", "poisson")
    },
}


@pytest.mark.parametrize("name", list(CAMERAS))
def test_closed_form_laws_equal_the_camera_at_hard_points(name):
    # 1e-9 absolute (plus last-bit rounding of huge |log p|, see close): the same formulas
    camera = CAMERAS[name]
    c, lam = grid_points(camera)
    jm = JaxModel.from_model(Model(5, 100.0, camera))
    tier = camera.likelihood
    closed_form = name.startswith("no-readout-") and tier not in ("gaussian", "poisson")
    assert jm.law == ("readout-free" if closed_form else tier)
    want = camera.log_likelihood_unchecked(c, lam)
    assert close(pixel_ll(jm, c, lam), want, atol=1e-9)
    assert np.isfinite(want).sum() > 100
    assert np.isneginf(want).any() == (
        jm.law in ("poisson", "readout-free") or name == "no-readout-gaussian"
    )


def test_photon_law_equals_the_camera():
    k, lam = np.meshgrid([0.0, 1.0, 2.0, 10.0, 1e3, 1e6], LAMS, indexing="ij")
    jm = JaxModel.from_model(Model(5, 100.0, Photon()))
    want = Photon().log_likelihood_unchecked(k.ravel(), lam.ravel())
    assert close(pixel_ll(jm, k.ravel(), lam.ravel()), want, atol=1e-9)


def on_table(camera, c, lam):
    """Where the NumPy table tier does not integrate: interpolated (its score is defined
    there), the readout alone at lam = 0, or the small-lam expansion."""
    t, r = camera.gain_units(c), camera.readout_in_gain_units
    _, score = table.log_and_score_table(t, lam, r)
    small = (lam > 0) & (lam < table.LAM_MIN) & (lam * (np.abs(t) + r) <= table.SMALL_LAM_REACH)
    return ~np.isnan(score) | (lam == 0) | small


def test_table_tier_equals_the_camera_on_its_grids():
    # the same interpolant from the same coefficients: 1e-9 absolute (plus last-bit rounding);
    # the points include lam = 0, the small-lam expansion, LAM_MIN and LAM_MAX, the offset
    camera = EMCCD(**TYPICAL, likelihood="table")
    c, lam = grid_points(camera)
    rng = np.random.default_rng(2)
    lam_law = 10 ** rng.uniform(-6, 5, 3000)
    c = np.concatenate([c, EMCCD(**TYPICAL).sample(lam_law, rng)])
    lam = np.concatenate([lam, lam_law])
    on = on_table(camera, c, lam)
    assert on.sum() > 3000 and (~on).sum() > 50
    jm = JaxModel.from_model(Model(5, 100.0, camera))
    got = np.asarray(pixel_ll(jm, c, lam))
    assert close(got[on], camera.log_likelihood_unchecked(c[on], lam[on]), atol=1e-9)
    assert np.all(np.isfinite(got))


def test_table_tier_off_its_grids_is_the_high_gain_closed_form_within_the_measured_bound():
    # Off the grids NumPy integrates the exact law (quadrature); JAX uses the high-gain closed
    # form with readout. Measured for readout/gain r = 0.25 (this camera), 4000 points each:
    #   counts beyond ETA_MAX of the bulk:  |diff| <= 1.9 (1.1% of |log p|), log p < -65
    #   counts < -NEAR r (below offset):     |diff| <= 926 (1.8% of |log p|), log p < -70
    #   lam < LAM_MIN beyond the expansion:  |diff| <= 0.03 (3e-5 of |log p|), log p < -1000
    #   lam > LAM_MAX:                       |diff| <= 1.2e-5 in the bulk (log p > -50),
    #                                        <= 2.4e-7 of |log p| in the tails
    # (with r = 2, the table's largest: 8.4, 4.2e3, 2 and 7.5e-4, up to 12% of |log p|).
    camera = EMCCD(**TYPICAL, likelihood="table")
    r = camera.readout_in_gain_units
    rng = np.random.default_rng(0)
    n = 100
    lam = 10 ** rng.uniform(-6, 5, n)
    eta = rng.choice([-1.0, 1.0], n) * rng.uniform(8.0, 14.0, n)
    t_eta = table._t_from_v(eta + np.sqrt(lam), r)
    keep = np.abs(t_eta) >= table.NEAR * r
    lam_small = 10 ** rng.uniform(-9, -6, n) * 0.999
    lam_big = 10 ** rng.uniform(5.1, 7, n)  # the grid's last node is 1.02e5
    cases = {
        "eta": (t_eta[keep], lam[keep]),
        "below": (-r * rng.uniform(12.0, 20.0, n), 10 ** rng.uniform(-6, 5, n)),
        "small": (1e-3 / lam_small * rng.uniform(1.0, 3.0, n), lam_small),
        "above": (lam_big + rng.normal(0, 3, n) * np.sqrt(2 * lam_big + r * r), lam_big),
    }
    jm = JaxModel.from_model(Model(5, 100.0, camera))
    bounds = {"eta": 0.02, "below": 0.03, "small": 1e-4}
    for name, (t, lam) in cases.items():
        counts = camera.offset + t * camera.gain / camera.e_per_adu
        assert not on_table(camera, counts, lam).any()
        want = camera.log_likelihood_unchecked(counts, lam)
        diff = np.abs(np.asarray(pixel_ll(jm, counts, lam)) - want)
        if name == "above":
            bulk = want > -50
            assert bulk.sum() > 30 and diff[bulk].max() <= 2e-5
            assert np.all(diff[~bulk] <= 1e-6 * np.abs(want[~bulk]))
        else:
            assert want.max() < -50
            assert np.all(diff <= bounds[name] * np.abs(want)), name


# ---------------------------------------------------------------------------- whole ROIs


@pytest.mark.parametrize("name", SCENES)
def test_log_likelihood_of_draws_equals_the_model(scenes, name):
    # summed over 225-361 pixels: 1e-12 relative (every pixel on the table's grids here)
    model, jm, counts, truth = scenes[name]
    rng = np.random.default_rng(5)
    draws = truth * (1 + 0.1 * rng.standard_normal((8, *truth.shape)))
    draws[..., 5] = np.abs(draws[..., 5])
    draws[0, :, 5] = 0.0  # no background
    want = model.log_likelihood(counts, draws)
    got = np.asarray(log_likelihood(jm, counts, draws))
    assert np.isfinite(want).all()
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)


def test_log_prior_equals_the_model_inside_outside_and_nan():
    prior = {
        "x0": {"kind": "normal", "mean": 10.0, "sd": 50.0},
        "y0": {"kind": "uniform", "low": -700.0, "high": 700.0},
        "s_x": {"kind": "log-uniform", "low": 10.0, "high": 1500.0},
        "s_y": {"kind": "half-normal", "scale": 300.0},
        "N": {"kind": "log-uniform", "low": 1.0, "high": 1e8},
        "b": {"kind": "half-normal", "scale": 5.0},
    }
    rng = np.random.default_rng(3)
    for model in (Model(15, 100.0, Photon(), prior), Model.from_scene(load_scene("ideal"))):
        p = np.column_stack(
            [rng.normal(0, 400, (60, 2)), 10 ** rng.uniform(0.5, 3.5, (60, 2)),
             10 ** rng.uniform(-1, 9, 60), rng.normal(5, 10, 60)]
        )  # fmt: skip
        p[0] = np.nan
        p[1, 3] = np.nan
        p[2, :] = [0.0, 700.0, 10.0, 0.0, 1.0, 0.0]  # on the support's edges
        want = model.log_prior(p)
        got = np.asarray(log_prior(JaxModel.from_model(model), p))
        assert np.isneginf(want).sum() > 5 and np.isfinite(want).sum() > 5
        assert np.array_equal(np.isneginf(got), np.isneginf(want))
        np.testing.assert_allclose(got, want, rtol=1e-14, atol=1e-14)


def test_gradient_equals_central_differences_of_the_numpy_likelihood(scenes):
    # jax.grad against central differences of Model.log_likelihood: 1e-5 relative (the
    # differences' truncation and rounding are ~1e-8 at these steps)
    for name in SCENES:
        model, jm, counts, truth = scenes[name]
        p = truth[:3].copy()
        p[1:, 5] = [0.3, 1.0]
        g = np.asarray(value_and_gradient(jm, counts[:3], p)[1])
        for k in range(3):
            fd = np.empty(6)
            for j in range(6):
                h = 1e-5 * max(abs(p[k, j]), 10.0)
                up, down = p[k].copy(), p[k].copy()
                up[j] += h
                down[j] -= h
                c = counts[k]
                fd[j] = (model.log_likelihood(c, up) - model.log_likelihood(c, down)) / (2 * h)
            np.testing.assert_allclose(
                g[k], fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max(), err_msg=name
            )


def test_no_nan_gradients_at_zero_background(scenes):
    for name in SCENES:
        _, jm, counts, truth = scenes[name]
        p = truth[:3].copy()
        p[:, 5] = 0.0
        if name == "emccd-typical":  # a narrow spot: far pixels hold lam ~1e-300 down to 0
            p[1, 2:4] = 15.0  # (under the other laws a count there is impossible: -inf)
        value, grad = value_and_gradient(jm, counts[:3], p)
        assert np.isfinite(np.asarray(value)).all() and np.isfinite(np.asarray(grad)).all(), name
    # the Hessian (the Laplace covariance's) of the table law at b = 0: finite for spots of
    # the scene's width. (At the narrow spot above, pixels far from it with counts ~50 readout
    # SDs above the offset have p ~ lam < 1e-154, and d2 log L / db2 ~ -sum 1 / lam**2 is
    # beyond the double range: -inf there is the correctly rounded value.)
    _, jm, counts, truth = scenes["emccd-typical"]
    p = truth[:2].copy()
    p[:, 5] = 0.0
    hessian = jax.jit(jax.vmap(jax.hessian(jm.log_likelihood, argnums=1)))(counts[:2], p)
    assert np.isfinite(np.asarray(hessian)).all()


def test_table_gradient_finite_at_the_grid_edges():
    camera = EMCCD(**TYPICAL, likelihood="table")
    r = camera.readout_in_gain_units
    lam = np.array(
        [0.0, 1e-300, table.LAM_MIN * (1 - 1e-15), table.LAM_MIN, table.LAM_MIN * (1 + 1e-15),
         0.5, 50.0, table.LAM_MAX * (1 - 1e-15), table.LAM_MAX, table.LAM_MAX * (1 + 1e-15)]
    )  # fmt: skip
    near = table.NEAR * r
    edges = np.array([0.0, near, near * (1 + 1e-15), -near, -near * (1 + 1e-15)])
    bulk = table._t_from_v(np.sqrt(lam)[:, None] + np.array([table.ETA_MAX, -table.ETA_MAX]), r)
    t = np.concatenate([np.broadcast_to(edges, (len(lam), 5)), bulk], axis=1).ravel()
    counts = camera.offset + t * camera.gain / camera.e_per_adu
    lam = np.repeat(lam, 7)
    jm = JaxModel.from_model(Model(5, 100.0, camera))
    value, first, second = map(np.asarray, pixel_derivatives(jm, counts, lam))
    assert np.isfinite(value).all() and np.isfinite(first).all()
    assert not np.isnan(second).any()
    # -inf only where the true value, ~ -1/lam**2 (lam = 1e-300 far above the offset, where
    # p ~ lam), is beyond the double range
    assert np.isfinite(second[(lam > 1e-150) | (np.abs(t) < 5.0)]).all()


def test_fisher_information_equals_the_camera():
    # 1e-10 relative: the same spline coefficients (log10 may differ in the last bit)
    lam = np.concatenate([10 ** np.linspace(-6, 8, 211), [1e-6, 1e6, 1e6 * (1 + 1e-15), 3e9]])
    for camera in (EMCCD(**TYPICAL, likelihood="table"), EMCCD(1.0), Photon()):
        jm = JaxModel.from_model(Model(5, 100.0, camera))
        got = np.asarray(fisher(jm, np.append(lam, [0.0, 1e-7])))
        np.testing.assert_allclose(
            got[:-2], camera.fisher_information_unchecked(lam), rtol=1e-10, atol=0
        )
        assert np.isposinf(got[-2])
        # below the EMCCD table NumPy integrates by quadrature; JAX returns NaN
        assert np.isnan(got[-1]) == isinstance(camera, EMCCD)


def test_jit_vmap_and_the_model_as_a_jit_argument(scenes):
    model, jm, counts, truth = scenes["emccd-typical"]
    leaves, tree = jax.tree_util.tree_flatten(jm)
    assert all(leaf.dtype == jnp.float64 for leaf in leaves) and len(leaves) == 7
    rebuilt = jax.tree_util.tree_unflatten(tree, leaves)
    assert rebuilt.law == "table" and rebuilt.roi == model.roi

    value, _ = value_and_gradient(jm, counts[:3], truth[:3])  # jit of vmap
    np.testing.assert_allclose(value, model.log_likelihood(counts[:3], truth[:3]), rtol=1e-12)
    draws = truth[:, None] * np.array([[1.0], [1.01], [0.99]])  # counts broadcast over draws
    got = np.asarray(log_likelihood(jm, counts[:, None], draws))
    np.testing.assert_allclose(got, model.log_likelihood(counts[:, None], draws), rtol=1e-12)


# ---------------------------------------------------------------------------- refusals


def test_unsupported_laws_are_refused_by_name():
    enable_x64()
    enable_x64()  # idempotent
    assert jax.config.jax_enable_x64
    assert set(SUPPORTED) == {"photon", "readout-free", "table", "high-gain", "gaussian", "poisson"}
    with pytest.raises(BayespsfInputError, match="sCMOS camera law yet; use backend='numpy'"):
        JaxModel.from_model(Model.from_scene(load_scene("scmos-typical")))
    with pytest.raises(BayespsfInputError, match=r"'exact'.*likelihood='table'.*backend='numpy'"):
        JaxModel.from_model(Model(5, 100.0, EMCCD(**TYPICAL, likelihood="exact")))
    with pytest.raises(BayespsfInputError, match=r"'table' tier at readout_sd / gain = 0\.005"):
        JaxModel.from_model(Model(5, 100.0, EMCCD(1000.0, 5.0, likelihood="table")))
    model = Model(5, 100.0, Photon())
    model.pixel_model = "airy"
    with pytest.raises(BayespsfInputError, match="pixel_model='airy'"):
        JaxModel.from_model(model)


def test_the_table_goes_to_the_device_once_per_camera_table():
    # two models of one camera share the camera's table: one device copy, equal to it; the
    # last TABLES_KEPT tables are kept; release_tables lets them go
    scene = load_scene("emccd-typical")
    first, second = (JaxModel.from_model(Model.from_scene(scene)) for _ in range(2))
    host = Model.from_scene(scene).camera.law_arrays()["table"]["coefficients"]
    assert first.table is second.table
    np.testing.assert_array_equal(np.asarray(first.table), host)
    kept = [np.arange(3.0) + k for k in range(TABLES_KEPT + 1)]
    copies = [on_device(a) for a in kept]
    assert on_device(kept[-1]) is copies[-1] and on_device(kept[0]) is not copies[0]
    release_tables()
    assert JaxModel.from_model(Model.from_scene(scene)).table is not first.table
