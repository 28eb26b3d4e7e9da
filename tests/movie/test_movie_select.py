"""The paper's selection rules on tables built to trip each rule once: who is removed, by
which rule, in which order, and the report's counts."""

from dataclasses import fields

import numpy as np
import pandas as pd
import pytest

from bayespsf.errors import BayespsfInputError
from bayespsf.movie import Rules, select
from bayespsf.movie.select import RULES, SETTING_RULES, report_markdown

FRAMES = 120


def tables():
    """Seven molecules: 0 passes every rule; 1 has two steps; 2 drifts; 3 has too few frames
    within 20% of its mean photons; 4 has dim frames (SNR); 5 has unequal widths; 6 is too
    wide. Every molecule bleaches at frame 100."""
    rng = np.random.default_rng(0)
    molecules = pd.DataFrame(
        {
            "molecule": range(7),
            "steps": [1, 2, 1, 1, 1, 1, 1],
            "drift_x": [0.1, 0, 2.0, 0, 0, 0, 0],
            "drift_x_se": 0.1,
            "drift_y": 0.0,
            "drift_y_se": 0.1,
        }
    )
    rows = []
    for m in range(7):
        for f in range(FRAMES):
            photons = 1000 * (1 + 0.05 * rng.standard_normal())
            if m == 3 and f % 2:
                photons *= 1.6  # half its frames far from its mean
            peak = 5.0 if (m == 4 and f < 60) else 50.0  # SNR 5 / sqrt(5 + 4) = 1.7 < 2.5
            s_x, s_y = 120.0, (140.0 if m == 5 else 121.0)
            if m == 6:
                s_x, s_y = 140.0, 141.0
            rows.append(
                {
                    "molecule": m,
                    "frame": f,
                    "photons": photons,
                    "peak": peak,
                    "background_var": 4.0,
                    "s_x": s_x,
                    "s_y": s_y,
                    "before_bleach": f < 100,
                }
            )
    return molecules, pd.DataFrame(rows)


def test_each_rule_removes_its_molecule_in_order():
    mol, fr, _ = select(*tables())
    assert mol["rejected_by"].tolist() == [
        "",
        "single_step",
        "no_drift",
        "photon_window",
        "photon_window",
        "equal_widths",
        "width_range",
    ]
    # molecule 4 lost 60 frames to the SNR rule, leaving 40 < 75: removed by the frame count
    assert (fr[(fr["molecule"] == 4)]["rejected_by"] == "snr").sum() == 60
    assert mol.loc[0, "selected"] and mol.loc[0, "valid_frames"] == 100
    assert not fr.loc[fr["frame"] >= 100, "valid"].any()


def test_the_report_counts_molecules_and_frames_per_rule():
    _, _, report = select(*tables())
    assert report["rule"].tolist() == ["frames before bleaching", *RULES]
    assert report["molecules left"].tolist() == [7, 6, 5, 5, 3, 2, 1]
    assert report["molecules removed"].sum() == 6
    # frames: the two-step and drifting molecules take 100 each; the SNR rule 60 frames
    assert report.set_index("rule").loc["snr", "frames removed"] == 60
    assert report["frames left"].iloc[0] == 700 and report["frames left"].iloc[-1] == 100
    text = report_markdown(report)
    assert "DeSantis" in text and "min_valid_frames = 75" in text and "| snr" in text
    # a skipped rule's settings are not listed as if they applied (--rules none listed them)
    skipped = report_markdown(report, Rules(skip=("photon_window",)))
    assert "min_valid_frames" not in skipped and "photon_tolerance" not in skipped
    assert "min_snr = 2.5" in skipped and "Skipped: photon_window." in skipped
    assert "Settings: none. Skipped: " in report_markdown(report, Rules(skip=RULES))
    assert set(SETTING_RULES) == {f.name for f in fields(Rules)} - {"skip"}
    assert set(SETTING_RULES.values()) <= set(RULES)


def test_rules_are_configurable_and_can_be_skipped():
    mol, _, report = select(*tables(), Rules(width_high=150.0, skip=("single_step",)))
    assert mol.loc[1, "selected"] and mol.loc[6, "selected"]
    assert report["rule"].iloc[1] == "single_step (skipped)"
    mol, _, _ = select(*tables(), Rules(min_valid_frames=30))
    assert mol.loc[4, "selected"]  # 40 valid frames are now enough


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"photon_tolerance": 0}, "photon_tolerance"),
        ({"min_valid_frames": 0}, "min_valid_frames must be a whole number >= 1, got 0"),
        ({"min_valid_frames": -5}, "min_valid_frames must be a whole number >= 1, got -5"),
        ({"min_valid_frames": float("nan")}, "min_valid_frames must be a whole number >= 1, got n"),
        ({"width_low": 200.0}, "width_low"),
        ({"width_low": 200.0, "width_high": 150.0}, "width_low must be in"),
        ({"skip": ("nope",)}, "unknown rules"),
        ({"min_snr": float("nan")}, "min_snr"),
        ({"drift_sigmas": "3"}, "drift_sigmas must be a number"),
        ({"photon_tolerance": None}, "photon_tolerance must be a number"),
        ({"min_valid_frames": float("inf")}, "min_valid_frames must be a whole number >= 1, got i"),
        ({"width_difference_fraction": float("nan")}, "width_difference_fraction"),
        ({"skip": "snr"}, r"skip must be a tuple of rule names, e.g. \('snr',\)"),
    ],
)
def test_bad_settings_are_named(kwargs, words):
    with pytest.raises(BayespsfInputError, match=words):
        Rules(**kwargs)


def test_missing_columns_are_named():
    molecules, frames = tables()
    with pytest.raises(BayespsfInputError, match="peak"):
        select(molecules, frames.drop(columns="peak"))


def test_the_width_range_follows_the_spots_sd():
    # the paper's 95-135 nm brackets its in-focus SD of 120 nm; another SD scales it, a range
    # that is given is kept, and without an SD the paper's own applies
    assert (Rules().for_psf(None).width_low, Rules().for_psf(None).width_high) == (95.0, 135.0)
    assert (Rules().for_psf(120.0).width_low, Rules().for_psf(120.0).width_high) == (95.0, 135.0)
    wide = Rules().for_psf(160.0)
    assert wide.width_low == pytest.approx(95 * 4 / 3) and wide.width_high == pytest.approx(180)
    given = Rules(width_low=90.0, width_high=150.0)
    assert given.for_psf(160.0) == given
    assert Rules(width_high=150.0).for_psf(160.0).width_low == pytest.approx(95 * 4 / 3)
    with pytest.raises(BayespsfInputError, match=r"width_low .* is above width_high"):
        Rules(width_high=120.0).for_psf(160.0)


def test_a_min_valid_frames_beyond_int64_is_a_whole_number():
    # np.isfinite(10**30) raised numpy's TypeError (an int beyond int64 is an object)
    assert Rules(min_valid_frames=10**30).min_valid_frames == 10**30
