"""Summary rows of many posteriors at once (``draws_rows``): each the row ``draws_row`` gives
its posterior alone, and both the row of the plain definition (numpy's mean, SD and quantile
of the draws, the truth's rank among draws chosen by the seed's generator), bit for bit."""

import struct

import numpy as np
import pytest

from bayespsf.errors import BayespsfInputError
from bayespsf.inference.gof import FIT_KEYS
from bayespsf.inference.summary import (
    QUANTILES,
    RANK_DRAWS,
    draws_row,
    draws_rows,
    quantile_column,
)
from bayespsf.psf import PARAMETER_NAMES

# 400: the default ESS; 98, 99, 100: either side of RANK_DRAWS; 2, 3: the fewest with an SD
COUNTS = (400, 2, 401, 98, 99, 100, 3, 400, 1000, 57, 400, 99)


def reference_row(flat, index, seed, info, truth=None, independent=None):
    """The row by its definition, one value at a time."""
    converged = bool(info.get("converged", False))
    row = {
        "molecule": int(index),
        "seed": int(seed),
        "converged": converged,
        "status": "converged" if converged else "not converged",
        "message": info.get("diagnosis") or ("" if converged else info.get("why", "")),
        "method": info.get("method", "mcmc"),
        "why": info.get("why", ""),
        "steps": int(info.get("steps", 0)),
        "draws": int(flat.shape[0]),
        "acceptance": float(info.get("acceptance", np.nan)),
        "seconds": float(info.get("seconds", np.nan)),
    }
    spaced = flat if independent is None else independent
    ranked = truth is not None and len(spaced) >= RANK_DRAWS
    if ranked:
        pick = np.random.default_rng([seed, 1]).choice(len(spaced), RANK_DRAWS, replace=False)
    quantiles = np.quantile(flat, QUANTILES, axis=0)
    means, sds = np.mean(flat, axis=0), np.std(flat, axis=0, ddof=1)
    for k, name in enumerate(PARAMETER_NAMES):
        row[f"{name}_mean"] = float(means[k])
        row[f"{name}_sd"] = float(sds[k])
        for q, value in zip(QUANTILES, quantiles[:, k], strict=True):
            row[quantile_column(name, q)] = float(value)
        row[f"{name}_tau"] = 1.0
        row[f"{name}_ess"] = float(info["ess"])
        if truth is not None:
            row[f"{name}_truth"] = float(truth[k])
            row[f"{name}_rank"] = int(np.sum(spaced[pick, k] < truth[k])) if ranked else np.nan
    row |= {key: info[key] for key in FIT_KEYS if key in info}
    return row


def assert_same_row(row, expected):
    """The same keys in the same order, the same types, and floats equal bit for bit (NaN
    included): a summary row is a deterministic function of the draws, so no tolerance."""
    assert list(row) == list(expected)
    for key, value in expected.items():
        assert type(row[key]) is type(value), key
        if isinstance(value, float):
            assert struct.pack("<d", row[key]) == struct.pack("<d", value), (key, row[key], value)
        else:
            assert row[key] == value, key


def posteriors(counts, seed=0, fit=True):
    """Draws of posteriors with ``counts`` draws each (x0 y0 s_x s_y N b on their scales),
    their seeds and sampler information (with the goodness-of-fit keys when ``fit``)."""
    rng = np.random.default_rng(seed)
    scale = np.array([20.0, 20.0, 10.0, 10.0, 300.0, 2.0])
    centre = np.array([0.0, 0.0, 130.0, 130.0, 2000.0, 10.0])
    draws = [centre + scale * rng.standard_normal((k, 6)) for k in counts]
    seeds = [int(s) for s in rng.integers(0, 2**63, len(counts))]
    infos = []
    for i, k in enumerate(counts):
        info = {"method": "importance", "ess": float(k), "converged": i % 3 > 0, "why": "w"}
        if fit:
            info |= {"chi2": 120.5 + i, "chi2_dof": 1.1, "chi2_p": 0.3, "chi2_at": "mean"}
        infos.append(info)
    truths = centre + scale * rng.standard_normal((len(counts), 6))
    return draws, seeds, infos, truths


@pytest.mark.parametrize("with_truth", [False, True])
@pytest.mark.parametrize("fit", [False, True])
def test_rows_equal_draws_row_and_the_definition(with_truth, fit):
    draws, seeds, infos, truths = posteriors(COUNTS, seed=1, fit=fit)
    truths = truths if with_truth else None
    indices = [10 * i + 3 for i in range(len(COUNTS))]
    rows = draws_rows(draws, indices, seeds, infos, truths)
    assert len(rows) == len(COUNTS)
    for i, row in enumerate(rows):
        truth = None if truths is None else truths[i]
        one = draws_row(draws[i], indices[i], seeds[i], infos[i], truth)
        assert_same_row(row, one)
        assert_same_row(row, reference_row(draws[i], indices[i], seeds[i], infos[i], truth))
        assert ("chi2" in row) == fit
        assert ("x0_rank" in row) == with_truth


def test_ranks_where_there_are_enough_draws_and_nan_below():
    draws, seeds, infos, truths = posteriors(COUNTS, seed=2)
    rows = draws_rows(draws, list(range(len(COUNTS))), seeds, infos, truths)
    for k, row in zip(COUNTS, rows, strict=True):
        ranks = [row[f"{name}_rank"] for name in PARAMETER_NAMES]
        if k < RANK_DRAWS:
            assert all(np.isnan(r) for r in ranks)
        else:
            assert all(isinstance(r, int) and 0 <= r <= RANK_DRAWS for r in ranks)


def test_the_same_row_whatever_the_other_posteriors():
    """A row depends on its own posterior only: alone, or among others of its size or not."""
    draws, seeds, infos, truths = posteriors(COUNTS, seed=3)
    rows = draws_rows(draws, list(range(len(COUNTS))), seeds, infos, truths)
    backwards = draws_rows(draws[::-1], list(range(len(COUNTS)))[::-1], seeds[::-1], infos[::-1])
    for row, other in zip(rows, backwards[::-1], strict=True):
        assert_same_row(
            {k: v for k, v in row.items() if not k.endswith(("_truth", "_rank"))}, other
        )


def test_many_posteriors_of_one_size_in_several_blocks():
    """More posteriors of one size than one array operation takes: the same rows."""
    counts = (120,) * 150
    draws, seeds, infos, truths = posteriors(counts, seed=4)
    rows = draws_rows(draws, list(range(150)), seeds, infos, truths)
    for i in (0, 63, 64, 127, 128, 149):
        assert_same_row(rows[i], reference_row(draws[i], i, seeds[i], infos[i], truths[i]))


@pytest.mark.parametrize("k", [*range(2, 60), 98, 99, 100, 101, 399, 400, 401, 1000, 1001])
def test_quantiles_are_numpys_for_every_size(k):
    """The quantiles are np.quantile's (its linear method) for posteriors of any size."""
    rng = np.random.default_rng(k)
    flat = rng.standard_normal((k, 6)) * [1e-3, 1.0, 7.0, 1e2, 1e4, 1e6] + 3.0
    row = draws_rows([flat, flat[::-1]], [0, 1], [5, 6], [{"ess": 1.0}] * 2)[0]
    expected = np.quantile(flat, QUANTILES, axis=0)
    for j, name in enumerate(PARAMETER_NAMES):
        got = [row[quantile_column(name, q)] for q in QUANTILES]
        assert np.array_equal(got, expected[:, j])  # exact: the same arithmetic as numpy's


def test_nan_and_infinite_draws_as_numpy_has_them():
    """A parameter with a NaN draw has NaN quantiles, as np.quantile gives; infinities give
    numpy's values too."""
    flat = np.random.default_rng(8).standard_normal((200, 6))
    flat[17, 1] = np.nan
    flat[3, 2], flat[4, 3] = np.inf, -np.inf
    with np.errstate(invalid="ignore"):
        row = draws_rows([flat], [0], [1], [{"ess": 200.0}])[0]
        expected = np.quantile(flat, QUANTILES, axis=0)
    for j, name in enumerate(PARAMETER_NAMES):
        got = [row[quantile_column(name, q)] for q in QUANTILES]
        assert np.array_equal(got, expected[:, j], equal_nan=True)
    assert np.isnan(row["y0_q0500"])


def test_draws_row_ranks_among_the_independent_draws():
    """With ``independent``, ranks come from those draws, tau and ESS per parameter."""
    rng = np.random.default_rng(9)
    flat = rng.standard_normal((300, 6))
    independent = flat[::2]
    truth = rng.standard_normal(6)
    tau = np.arange(1.0, 7.0)
    row = draws_row(flat, 4, 77, {"ess": 0.0}, truth, independent, tau, 300 / tau)
    pick = np.random.default_rng([77, 1]).choice(len(independent), RANK_DRAWS, replace=False)
    for k, name in enumerate(PARAMETER_NAMES):
        assert row[f"{name}_rank"] == int(np.sum(independent[pick, k] < truth[k]))
        assert row[f"{name}_tau"] == tau[k]
        assert row[f"{name}_ess"] == 300 / tau[k]
    short = draws_row(flat, 4, 77, {"ess": 0.0}, truth, flat[:50], tau, 300 / tau)
    assert np.isnan(short["x0_rank"])  # 50 near-independent draws: too few to rank


def test_no_posteriors_and_mismatched_lengths():
    assert draws_rows([], [], [], []) == []
    draws, seeds, infos, truths = posteriors((100, 100), seed=10)
    with pytest.raises(BayespsfInputError, match="one index, seed and info"):
        draws_rows(draws, [0], seeds, infos)
    with pytest.raises(BayespsfInputError, match="truths must hold 2 rows"):
        draws_rows(draws, [0, 1], seeds, infos, truths[:1])


def test_tables_concatenated_keep_their_seeds_whole():
    """A table's seeds are uint64 where one is at or above 2**63, else int64; ``pd.concat`` of
    the two rounds them to float64. ``concat_tables`` keeps them whole, as one
    ``pd.DataFrame`` of all the rows does, and leaves a table without seeds as it is."""
    import pandas as pd

    from bayespsf.inference.summary import concat_tables

    big, small = 2**64 - 5, 7
    rows = [{"molecule": 0, "seed": big}, {"molecule": 1, "seed": small}]
    tables = [pd.DataFrame(rows[:1]), pd.DataFrame(rows[1:])]
    assert {t["seed"].dtype.name for t in tables} == {"uint64", "int64"}
    joined = concat_tables(tables)
    pd.testing.assert_frame_equal(joined, pd.DataFrame(rows))
    assert joined["seed"].tolist() == [big, small]
    plain = concat_tables([pd.DataFrame({"molecule": [0]}), pd.DataFrame({"molecule": [1]})])
    assert plain["molecule"].tolist() == [0, 1]


def test_an_unconverged_row_without_a_diagnosis_says_why_in_its_message():
    # a Laplace or importance row that did not converge has no chain diagnosis: its message
    # is its ``why``
    from bayespsf.inference.summary import _row_head

    why = "chain: the Laplace covariance is not positive definite"
    assert _row_head(0, 1, {"converged": False, "why": why}, 0)["message"] == why
    assert _row_head(0, 1, {"converged": True, "why": why}, 0)["message"] == ""
    chain = {"converged": False, "why": why, "diagnosis": "tau grows with the chain"}
    assert _row_head(0, 1, chain, 0)["message"] == "tau grows with the chain"
