"""``bayespsf.inference.psis`` against ``arviz_stats``' PSIS, row by row: random batches of
several draw counts (either side of the 225-draw tail rule), light and heavy tails, draws
outside the support (-inf), the edge cases arviz_stats defines; batches of any leading shape;
NumPy and JAX (where installed) from the one implementation.

Tolerances: 1e-9 on log weights (absolute: they are logs) and on k-hat (absolute, k-hat is of
order 1). The two compute the same floating-point operations except the reductions'
summation order, which moves the results by ~1e-14; 1e-9 fails on a real difference of
algorithm (a prior of 11 draws instead of 10 moves k-hat by ~1e-3).
"""

import subprocess
import sys

import numpy as np
import pytest
from arviz_stats.base.array import array_stats

from bayespsf.inference.psis import psis, tail_length

TOL = 1e-9
DRAWS = [50, 224, 226, 520, 2000]


def reference(log_ratio):
    """arviz_stats' log weights and k-hat of one row (it smooths ``exp(-input)``)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        log_w, khat = array_stats.psislw(-np.asarray(log_ratio, dtype=float))
    return np.asarray(log_w), float(khat)


def batch(draws: int, seed: int) -> np.ndarray:
    """Rows of log ratios: importance weights of a Gaussian target under a wider Gaussian
    (bounded weights, k-hat < 0.5) and under narrower ones, Student-t ratios (k-hat > 0.7 at
    scale 3), and a row with draws outside the support."""
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((4, draws))
    rows = [
        # target N(0, 1), proposal N(0, 1.5^2): bounded weights
        -0.5 * (1.5 * z[0]) ** 2 + 0.5 * z[0] ** 2,
        # target N(0, 1), proposal N(0, s^2) with s < 1: Pareto weights of shape 1 - s^2
        -0.5 * (0.3 * z[1]) ** 2 + 0.5 * z[1] ** 2,
        -0.5 * (0.4 * z[2]) ** 2 + 0.5 * z[2] ** 2,
        3.0 * rng.standard_t(3, draws),
        0.1 * rng.standard_t(3, draws),
    ]
    outside = 2.0 * z[3]
    outside[rng.choice(draws, draws // 3, replace=False)] = -np.inf  # a third outside
    rows.append(outside)
    return np.array(rows)


def assert_rows_equal(log_w, khat, ref_w, ref_khat):
    """Equal within ``TOL``; infinities and NaN in the same places."""
    np.testing.assert_allclose(log_w, ref_w, rtol=0, atol=TOL)
    np.testing.assert_allclose(khat, ref_khat, rtol=0, atol=TOL)


@pytest.mark.parametrize("draws", DRAWS)
def test_rows_are_arviz_stats(draws):
    log_ratio = batch(draws, seed=draws)
    log_w, khat = psis(log_ratio)
    assert log_w.shape == log_ratio.shape and khat.shape == (len(log_ratio),)
    for row, w, k in zip(log_ratio, log_w, khat, strict=True):
        assert_rows_equal(w, k, *reference(row))
    assert khat[3] > 0.7 and khat[0] < 0.5  # both sides of arviz_stats' threshold
    assert np.isneginf(log_w[-1][np.isneginf(log_ratio[-1])]).all()


def test_tail_length_is_arviz_stats():
    for draws in [25, 50, 224, 225, 226, 520, 2000]:
        assert tail_length(draws) == array_stats._get_ps_tails(draws, 1, tail="right")


@pytest.mark.parametrize("draws", [50, 520])
def test_edge_cases_are_arviz_stats(draws):
    rng = np.random.default_rng(7)
    cases = {
        "mostly outside": np.where(np.arange(draws) < draws - draws // 10, -np.inf, 1.0),
        "all outside": np.full(draws, -np.inf),
        "a NaN": rng.standard_normal(draws),
        "an inf": rng.standard_normal(draws),
        "half tied at the top": np.where(np.arange(draws) < draws // 2, 2.0, 0.0),
    }
    cases["mostly outside"][-(draws // 10) :] = rng.standard_normal(draws // 10)
    cases["a NaN"][3] = np.nan
    cases["an inf"][3] = np.inf
    cases["half tied at the top"] += 0.5 * rng.standard_normal(draws) * (np.arange(draws) % 3 == 0)
    log_w, khat = psis(np.array(list(cases.values())))
    for i, row in enumerate(cases.values()):
        assert_rows_equal(log_w[i], khat[i], *reference(row))
    assert np.isinf(khat[1]) and np.isnan(log_w[1]).all()  # nothing to fit: undefined
    assert np.isnan(log_w[2]).all() and np.isnan(log_w[3]).all()


def test_a_flat_tail_is_nan_where_arviz_stats_raises():
    rng = np.random.default_rng(3)
    log_ratio = np.stack([np.full(100, 1.0), rng.standard_normal(100)])
    log_ratio[1, :30] = 5.0  # the 20 tail draws are equal
    with pytest.raises(ValueError, match="same"):
        reference(log_ratio[1])
    log_w, khat = psis(log_ratio)
    assert np.isnan(khat).all()
    # the weights are the unsmoothed normalised ones
    expected = log_ratio - np.log(np.sum(np.exp(log_ratio), axis=-1, keepdims=True))
    np.testing.assert_allclose(log_w, expected, rtol=0, atol=TOL)


def test_too_few_draws_are_refused_as_by_arviz_stats():
    with pytest.raises(ValueError, match="at least 5"):
        psis(np.zeros(24))
    with pytest.raises(ValueError):
        reference(np.random.default_rng(0).standard_normal(24))


def test_a_batch_of_any_shape_is_its_rows():
    rng = np.random.default_rng(11)
    log_ratio = 2.0 * rng.standard_t(4, (3, 4, 300))
    log_ratio[1, 2, ::5] = -np.inf
    log_w, khat = psis(log_ratio)
    assert log_w.shape == (3, 4, 300) and khat.shape == (3, 4)
    for i in range(3):
        for j in range(4):
            one_w, one_khat = psis(log_ratio[i, j])
            assert one_khat.shape == ()
            np.testing.assert_array_equal(log_w[i, j], one_w)  # the same operations
            np.testing.assert_array_equal(khat[i, j], one_khat)


def test_many_rows_run_in_blocks_and_equal_their_rows(monkeypatch):
    import bayespsf.inference.psis as module

    log_ratio = batch(226, seed=5)
    whole = psis(log_ratio)
    monkeypatch.setattr(module, "BLOCK_BYTES", 1)  # one row per block
    blocked = psis(log_ratio)
    for a, b in zip(whole, blocked, strict=True):
        np.testing.assert_array_equal(a, b)


def test_numpy_alone_runs_it():
    """Without JAX (blocked from import), the module imports and computes."""
    code = (
        "import sys; sys.modules['jax'] = None; import numpy as np; "
        "from bayespsf.inference.psis import psis; "
        "print(psis(np.linspace(0.0, 1.0, 30))[1])"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert np.isfinite(float(run.stdout))


@pytest.mark.parametrize("draws", DRAWS)
def test_jax_is_numpy(draws):
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    from bayespsf.inference.backends import start_jax

    start_jax()  # float64, whichever test a worker ran first
    log_ratio = batch(draws, seed=draws + 1)
    log_w, khat = psis(log_ratio)
    compiled = jax.jit(lambda x: psis(x, xp=jnp))
    mapped = jax.jit(jax.vmap(lambda x: psis(x, xp=jnp)))  # as jax_sampling maps it
    for jax_w, jax_khat in (compiled(jnp.asarray(log_ratio)), mapped(jnp.asarray(log_ratio))):
        assert_rows_equal(np.asarray(jax_w), np.asarray(jax_khat), log_w, khat)


def test_jax_edge_cases_are_numpy():
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    from bayespsf.inference.backends import start_jax

    start_jax()
    rng = np.random.default_rng(2)
    rows = np.stack([rng.standard_normal(100) for _ in range(4)])
    rows[0] = -np.inf
    rows[1, 3] = np.nan
    rows[2, :30] = 5.0  # a flat tail
    rows[3, :50] = -np.inf
    log_w, khat = psis(rows)
    jax_w, jax_khat = jax.jit(lambda x: psis(x, xp=jnp))(jnp.asarray(rows))
    assert_rows_equal(np.asarray(jax_w), np.asarray(jax_khat), log_w, khat)


def test_tied_tail_draws_get_the_same_weights_in_both_libraries():
    """Where draws with equal ratios share the tail (here 90% of draws outside the support),
    NumPy's sort (arviz_stats') and JAX's stable sort order them differently: the tied draws
    get the same set of smoothed weights, in another order."""
    jax = pytest.importorskip("jax")
    import jax.numpy as jnp

    from bayespsf.inference.backends import start_jax

    start_jax()
    row = np.random.default_rng(4).standard_normal(520)
    row[:468] = -np.inf  # 16 of the 68 tail draws at -inf
    log_w, khat = psis(row)
    assert_rows_equal(log_w, khat, *reference(row))
    jax_w, jax_khat = jax.jit(lambda x: psis(x, xp=jnp))(jnp.asarray(row))
    np.testing.assert_allclose(float(jax_khat), khat, rtol=0, atol=TOL)
    np.testing.assert_allclose(np.sort(np.asarray(jax_w)), np.sort(log_w), rtol=0, atol=TOL)
    np.testing.assert_allclose(np.asarray(jax_w)[468:], log_w[468:], rtol=0, atol=TOL)
