"""The calibration check without ground truth (bayespsf.analysis.consistency), against normal
draws whose spread is known: calibrated SDs pass, SDs 20% too small fail."""

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from bayespsf.analysis import frame_consistency
from bayespsf.errors import BayespsfInputError


def synthetic(molecules=300, frames=12, understate=1.0, seed=0):
    """Per-frame posterior means ~ N(truth, s_k^2) with s_k from 5 to 15 nm; the table states
    s_k / understate as the SD."""
    rng = np.random.default_rng(seed)
    mol = np.repeat(np.arange(molecules), frames)
    sd = rng.uniform(5.0, 15.0, mol.size)
    truth = rng.uniform(-50, 50, molecules)[mol]
    table = pd.DataFrame({"molecule": mol, "frame": np.tile(np.arange(frames), molecules)})
    for p in ("x0", "y0", "s_x", "s_y"):
        table[f"{p}_mean"] = truth + 100 * (p[0] == "s") + rng.normal(0, sd)
        table[f"{p}_sd"] = sd / understate
    return table


def test_calibrated_posteriors_pass():
    # 3600 frames: z SD within 4 of its SEs of 1; the molecules' chi-square p-values uniform
    # (KS p > 0.001); coverage within 4 binomial SEs of its expected value
    frames, molecules, overall = frame_consistency(synthetic())
    for _, row in overall.iterrows():
        assert abs(row["z_sd"] - 1) < 4 * row["z_sd_se"], row
        assert abs(row["coverage"] - row["expected_coverage"]) < 4 * row["coverage_se"], row
        assert row["p_value"] > 1e-3 and row["dof"] == 300 * 11
    assert 0.95 < overall["expected_coverage"].min() < 0.96
    p = molecules.loc[molecules["parameter"] == "x0", "p_value"]
    assert stats.kstest(p, "uniform").pvalue > 1e-3
    assert frames["x0_z"].notna().all() and len(frames) == 3600


def test_understated_errors_fail_clearly():
    # SDs stated 20% small: z SD ~1.2, coverage ~0.91 against 0.96, chi-square p-value ~0
    _, _, overall = frame_consistency(synthetic(understate=1.2, seed=1))
    for _, row in overall.iterrows():
        assert row["z_sd"] - 1 > 10 * row["z_sd_se"], row
        assert row["expected_coverage"] - row["coverage"] > 6 * row["coverage_se"], row
        assert row["p_value"] < 1e-10


def test_overstated_errors_fail_two_sided():
    # SDs stated 20% large (a gain declared too high reads so): the chi-square is too small,
    # so its upper-tail p-value is ~1 and only the two-sided one is small
    _, _, overall = frame_consistency(synthetic(understate=1 / 1.2, seed=2))
    for _, row in overall.iterrows():
        assert 1 - row["z_sd"] > 6 * row["z_sd_se"], row
        assert row["p_value"] > 0.999 and row["p_two_sided"] < 1e-10, row
    # calibrated: the two-sided p-values of the molecules are uniform too
    _, calibrated, _ = frame_consistency(synthetic(seed=3))
    p = calibrated.loc[calibrated["parameter"] == "x0", "p_two_sided"]
    assert p.between(0, 1).all() and stats.kstest(p, "uniform").pvalue > 1e-3


def test_combined_estimate_is_the_weighted_mean():
    table = pd.DataFrame(
        {"molecule": [0, 0, 0], "x0_mean": [1.0, 2.0, 4.0], "x0_sd": [1.0, 2.0, 2.0]}
    )
    _, molecules, _ = frame_consistency(table, parameters=("x0",))
    w = np.array([1, 0.25, 0.25])
    assert molecules["combined"].iloc[0] == pytest.approx((w * [1, 2, 4]).sum() / w.sum())
    assert molecules["combined_se"].iloc[0] == pytest.approx(1 / np.sqrt(w.sum()))
    assert molecules["dof"].iloc[0] == 2


def test_single_frame_molecules_and_missing_values_are_left_out():
    table = synthetic(molecules=3, frames=4)
    table.loc[0, "x0_mean"] = np.nan
    table = pd.concat(
        [
            table,
            pd.DataFrame(
                {
                    "molecule": [9],
                    "x0_mean": [0.0],
                    "x0_sd": [1.0],
                    "y0_mean": [0.0],
                    "y0_sd": [1.0],
                    "s_x_mean": [1.0],
                    "s_x_sd": [1.0],
                    "s_y_mean": [1.0],
                    "s_y_sd": [1.0],
                }
            ),
        ]
    )
    frames, molecules, _ = frame_consistency(table)
    x0 = molecules[molecules["parameter"] == "x0"]
    assert x0["frames"].tolist() == [3, 4, 4] and 9 not in x0["molecule"].tolist()
    assert frames["x0_z"].isna().sum() == 2
    with pytest.raises(BayespsfInputError, match="no column"):
        frame_consistency(table.drop(columns="s_y_sd"))
    for bad in (0.0, -1.0, np.inf):
        with pytest.raises(BayespsfInputError, match="x0_sd not a finite number > 0"):
            frame_consistency(table.assign(x0_sd=bad))
    _, one, _ = frame_consistency(table, parameters="x0")  # one name, not its letters
    assert set(one["parameter"]) == {"x0"}


def test_molecules_of_one_frame_give_no_statistic_and_no_warning():
    # a one-frame movie: every molecule has one frame, which has no spread about its own
    # estimate (s^2 - 1/sum(w) is 0, or -1e-15 by rounding, whose square root once warned);
    # the check's statistics are NaN and nothing is warned (the suite turns warnings to errors)
    frames, molecules, overall = frame_consistency(synthetic(molecules=50, frames=1))
    assert frames["x0_z"].isna().all() and molecules.empty
    assert overall["frames"].eq(0).all() and overall["z_sd"].isna().all()
    assert overall["p_value"].isna().all()
