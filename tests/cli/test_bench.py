"""`bayespsf bench --quick`: the accuracy-time frontier runs end to end and measures what the
physics says it must (the run takes ~15 s on two cores, ~30 s where JAX's compiled programs
are not cached yet; no timing is asserted). It runs docs/cli.md's command exactly as written
(``DOCUMENTED``), in an empty folder with its default output folder, so the guide's own test
does not run it a second time. Without JAX the frontier skips its JAX rows and says so."""

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "repository"))
from test_commands_as_documented import _bash

DOCUMENTED = "bayespsf bench --quick --workers 2"


@pytest.fixture(scope="module")
def frontier(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bench")
    result = _bash(DOCUMENTED, folder)
    assert result.returncode == 0, result.stderr[-3000:]
    out = folder / "bayespsf-bench"
    return out, pd.read_csv(out / "frontier-summary.csv"), pd.read_csv(out / "frontier.csv")


def test_files_and_columns(frontier):
    out, summary, rows = frontier
    assert (out / "frontier.png").stat().st_size > 0
    assert "Which tier" in (out / "frontier.md").read_text()
    on_numpy = summary[~summary["method"].str.endswith("(JAX)")]
    assert set(on_numpy["method"]) == {"MLE + CRLB", "Laplace", "posterior", "importance"}
    assert set(summary.loc[summary["method"] == "posterior", "tier"]) == {
        "table",
        "high-gain",
        "gaussian",
        "poisson",
    }
    assert np.all(rows["time / MLE"] > 0) and np.all(rows["MLE seconds"] > 0)


def test_reference_is_the_exact_law(frontier):
    # the table is within 4e-5 of the exact log density per pixel: importance weights to the
    # exact law change the reference SD by far less than its Monte Carlo error (~1%)
    _, _, rows = frontier
    assert np.all(np.abs(rows["ref exact correction"]) < 1e-4)


def test_tiers_err_as_their_approximations_predict(frontier):
    _, summary, _ = frontier
    post = summary[summary["method"] == "posterior"].set_index(["level", "tier", "ESS target"])
    err = post["SD error (RMS)"]
    # the accurate tier against the reference: Monte Carlo error only; SD of the relative SD
    # error ~ sqrt(1/(2*2000) + 1/(2*4000)) = 1.9% at the ESS these runs reach, so 6% is 3 SDs
    assert np.all(err.xs("table", level="tier") < 0.06)
    # importance sampling stops near its ESS target (its first batch is ess / 0.77 draws):
    # 3 SDs of the relative SD error at the ESS it reached, against a reference of ESS ~4000
    importance = summary[summary["method"] == "importance"]
    assert np.all(importance["SD error (RMS)"] < importance_tolerance(importance["median ESS"]))
    # the Poisson tier ignores the EM register's excess noise (variance 2 lam, not lam), so its
    # posterior is too narrow by about 1/sqrt(2): an SD error near 0.29
    assert np.all(err.xs("poisson", level="tier") > 0.2)
    # at N = 5000 the Gaussian approximations (CRLB at the MLE, Laplace) are within 6% too
    cheap = summary[
        summary["method"].isin(["MLE + CRLB", "Laplace"]) & (summary["level"] == "high")
    ]
    assert np.all(cheap["SD error (RMS)"] < 0.06)


def importance_tolerance(ess):
    """3 SDs of the relative error of an SD estimated from draws of effective size ``ess``,
    against a reference of ESS ~4000 (the SD of a relative SD error is ~1/sqrt(2 ESS))."""
    return 3 * np.sqrt(1 / (2 * ess) + 1 / (2 * 4000))


def test_jax_rows_are_scored_like_the_numpy_rows(frontier):
    pytest.importorskip("jax")
    out, summary, rows = frontier
    on_jax = summary[summary["method"].str.endswith("(JAX)")]
    assert set(on_jax["method"]) == {"importance (JAX)", "auto (JAX)"}
    assert set(on_jax["level"]) == {"low", "high"} and set(on_jax["tier"]) == {"table"}
    assert (on_jax["ROIs it cannot score"] == 0).all()
    for column in ("SD error (RMS)", "mean offset (RMS, ref SDs)", "coverage 68%", "coverage 95%"):
        assert np.all(np.isfinite(on_jax[column])), column
    # the same posterior as the reference's within Monte Carlo error: the NumPy importance
    # rows' tolerance on the SD (at the ESS the JAX rows reached), and on the mean 3 SDs of
    # the offset of a mean of draws of that ESS from the reference's, in reference SDs
    assert np.all(on_jax["SD error (RMS)"] < importance_tolerance(on_jax["median ESS"]))
    offset_sd = np.sqrt(1 / on_jax["median ESS"] + 1 / 4000)
    assert np.all(on_jax["mean offset (RMS, ref SDs)"] < 3 * offset_sd)
    jax_rows = rows[rows["method"].str.endswith("(JAX)")]
    assert np.all(jax_rows["time / MLE"] > 0)
    assert "compilation excluded" in (out / "frontier.md").read_text()


def test_without_jax_the_frontier_has_numpy_rows_only_and_says_so(monkeypatch, tmp_path):
    from bayespsf.cli import bench

    monkeypatch.setitem(sys.modules, "jax", None)  # ``import jax`` raises ImportError
    plan = bench.Plan(
        photons={"high": 5000}, molecules=1, tiers=(), budgets=(100,),
        exact_budgets=(), exact_molecules=0, reference_ess=400.0, reweighted_draws=20,
    )  # fmt: skip
    said = []
    rows = bench.frontier(plan, workers=1, progress=said.append)
    assert set(rows["method"]) == {"MLE + CRLB", "Laplace", "importance"}
    assert bench.JAX_MISSING in said and 'pip install "bayespsf[jax]"' in bench.JAX_MISSING
    assert bench.JAX_MISSING in bench.report(rows, tmp_path, "test")
