"""The paper's selection rules, named, configurable and counted.

DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), section "Data acquisition and
selection": molecules whose time trace shows a single bleaching step were kept, and then only
those satisfying five conditions entered the width-precision analysis:

1. ``no_drift``: no drift of the centroid against time (here: neither axis' least-squares
   slope differs from zero by more than ``drift_sigmas`` standard errors);
2. ``photon_window``: frames whose photon count N lies within ``photon_tolerance`` (20%) of the
   molecule's mean ⟨N⟩ are valid, and a molecule needs at least ``min_valid_frames`` (75) of
   them (applied after rule 3 has removed its frames too);
3. ``snr``: frames with ``I0 / sqrt(I0 + sigma_b^2)`` above ``min_snr`` (2.5), where I0 is the
   peak pixel's photons minus the mean background and sigma_b^2 the background variance in
   photons;
4. ``equal_widths``: the mean s_x and mean s_y of the valid frames differ by at most
   ``width_difference_nm`` (10 nm) or ``width_difference_fraction`` (5%) of their mean;
5. ``width_range``: both mean widths lie between ``width_low`` and ``width_high`` (95 and
   135 nm).

The single bleaching step comes first (``single_step``). The rules run in the order of
``RULES``: single_step, no_drift, snr, photon_window, equal_widths, width_range (the paper's 1,
3, 2, 4, 5: the 75 valid frames of rule 2 are frames that pass rule 3 too), each on what the
previous ones left; frames after a molecule's bleaching step are never valid. The report says
how many molecules and frames each rule removed.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from bayespsf.errors import BayespsfInputError

MOLECULE_COLUMNS = ("molecule", "steps", "drift_x", "drift_x_se", "drift_y", "drift_y_se")
FRAME_COLUMNS = (
    "molecule",
    "frame",
    "photons",
    "peak",
    "background_var",
    "s_x",
    "s_y",
    "before_bleach",
)


@dataclass(frozen=True)
class Rules:
    """The selection rules' settings; the defaults are the paper's numbers.

    Parameters
    ----------
    drift_sigmas : float, default 3.0
        ``no_drift``: the largest centroid slope, in standard errors, on either axis.
    photon_tolerance : float, default 0.2
        ``photon_window``: a frame is valid when its photons N lie within this fraction of
        the molecule's mean ⟨N⟩ (in (0, 1)).
    min_valid_frames : int, default 75
        ``photon_window``: the fewest valid frames a molecule needs.
    min_snr : float, default 2.5
        ``snr``: a frame's ``I0 / sqrt(I0 + sigma_b^2)`` (photons) must exceed this.
    width_difference_nm : float, default 10.0
        ``equal_widths``: the largest difference of mean s_x and s_y in nm ...
    width_difference_fraction : float, default 0.05
        ... or as a fraction of their mean, whichever is larger.
    width_low, width_high : float, optional
        ``width_range``: both mean widths must lie in this range (nm). Default: the paper's
        95 and 135 nm, which bracket its in-focus spot SD of 120 nm, scaled by ``s0 / 120``
        for a movie whose spot SD ``s0`` (stated or estimated) is another (``for_psf``); an
        end that is given is kept.
    skip : tuple of str, default ()
        Names of rules (``RULES``) switched off.

    Raises
    ------
    BayespsfInputError
        A setting that is not a finite number >= 0, a ``photon_tolerance`` outside (0, 1),
        ``width_low > width_high``, a ``min_valid_frames`` that is not a whole number >= 1,
        or ``skip`` naming an unknown rule (or given as a string).

    See Also
    --------
    select : applies them.

    Notes
    -----
    The module docstring states each rule as DeSantis, DeCenzo, Li & Wang, Opt. Express 18
    (2010) applied it, and the order in which they run.
    """

    drift_sigmas: float = 3.0
    photon_tolerance: float = 0.2
    min_valid_frames: int = 75
    min_snr: float = 2.5
    width_difference_nm: float = 10.0
    width_difference_fraction: float = 0.05
    width_low: float | None = None
    width_high: float | None = None
    skip: tuple[str, ...] = ()

    def __post_init__(self):
        numbers = (
            "drift_sigmas",
            "photon_tolerance",
            "min_valid_frames",
            "min_snr",
            "width_difference_nm",
            "width_difference_fraction",
            "width_low",
            "width_high",
        )
        ends = ("width_low", "width_high")  # None: the paper's, scaled to the spot (for_psf)
        numbers = tuple(n for n in numbers if not (n in ends and getattr(self, n) is None))
        for name in numbers:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.number):
                raise BayespsfInputError(f"{name} must be a number, got {value!r}")
            if name != "min_valid_frames" and (not np.isfinite(value) or value < 0):  # below
                raise BayespsfInputError(f"{name} must be a finite number >= 0, got {value!r}")
        if not 0 < self.photon_tolerance < 1:
            raise BayespsfInputError("photon_tolerance must be in (0, 1), e.g. 0.2 for 20%")
        low = PAPER_WIDTHS[0] if self.width_low is None else self.width_low
        high = PAPER_WIDTHS[1] if self.width_high is None else self.width_high
        if not 0 <= low <= high:
            raise BayespsfInputError("width_low must be in [0, width_high]")
        frames = self.min_valid_frames
        if not np.isfinite(float(frames)) or int(frames) != frames or frames < 1:
            raise BayespsfInputError(
                f"min_valid_frames must be a whole number >= 1, got {frames!r}"
            )
        if isinstance(self.skip, str):
            raise BayespsfInputError(
                f"skip must be a tuple of rule names, e.g. ({self.skip!r},), got {self.skip!r}"
            )
        unknown = set(self.skip) - set(RULES)
        if unknown:
            raise BayespsfInputError(f"skip names unknown rules {sorted(unknown)}; rules: {RULES}")

    def for_psf(self, s0: float | None) -> Rules:
        """These rules with the width range resolved: each end as given, else the paper's
        (95 and 135 nm) scaled by ``s0 / 120`` (its in-focus spot SD), or the paper's own
        without ``s0``.

        Parameters
        ----------
        s0 : float or None
            The movie's spot SD in nm (stated or estimated).

        Returns
        -------
        Rules

        Raises
        ------
        BayespsfInputError
            If a given end and a scaled one cross.
        """
        scale = 1.0 if s0 is None else float(s0) / PAPER_S0
        low = PAPER_WIDTHS[0] * scale if self.width_low is None else self.width_low
        high = PAPER_WIDTHS[1] * scale if self.width_high is None else self.width_high
        if low > high:
            raise BayespsfInputError(
                f"width_low ({low:g} nm) is above width_high ({high:g} nm) at the spot's SD "
                f"of {s0:g} nm: give both ends of the width range"
            )
        return replace(self, width_low=low, width_high=high)


PAPER_S0 = 120.0  # nm: the in-focus spot SD the paper's width range brackets
PAPER_WIDTHS = (95.0, 135.0)  # nm: the paper's width range (its condition 5)
RULES = ("single_step", "no_drift", "snr", "photon_window", "equal_widths", "width_range")
SETTING_RULES = {  # each setting of ``Rules`` and the rule that uses it
    "drift_sigmas": "no_drift",
    "photon_tolerance": "photon_window",
    "min_valid_frames": "photon_window",
    "min_snr": "snr",
    "width_difference_nm": "equal_widths",
    "width_difference_fraction": "equal_widths",
    "width_low": "width_range",
    "width_high": "width_range",
}


def _require(table: pd.DataFrame, columns, name: str) -> None:
    missing = [c for c in columns if c not in table]
    if missing:
        raise BayespsfInputError(f"{name} lacks the column(s) {missing}")


def select(
    molecules: pd.DataFrame, frames: pd.DataFrame, rules: Rules | None = None
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Apply the paper's selection rules to molecules and their frames.

    Parameters
    ----------
    molecules : pandas.DataFrame
        One row per molecule with ``MOLECULE_COLUMNS``: ``molecule``, ``steps`` (bleaching
        steps), ``drift_x``, ``drift_x_se``, ``drift_y``, ``drift_y_se`` (centroid slopes
        and their standard errors, nm per frame).
    frames : pandas.DataFrame
        One row per molecule and frame with ``FRAME_COLUMNS``: ``molecule``, ``frame``,
        ``photons`` (N), ``peak`` (peak photons I0), ``background_var`` (photons²), ``s_x``,
        ``s_y`` (the frame's width estimates, nm) and ``before_bleach`` (the frame precedes
        the bleaching step).
    rules : Rules, optional
        The settings (default: the paper's).

    Returns
    -------
    molecules : pandas.DataFrame
        A copy of ``molecules`` with ``rejected_by`` (the first rule that removed the
        molecule, empty if selected), ``selected`` and ``valid_frames``.
    frames : pandas.DataFrame
        A copy of ``frames`` with ``rejected_by`` (``after bleaching``, ``snr`` or
        ``photon_window``; empty if kept) and ``valid``.
    report : pandas.DataFrame
        One row per rule, in order (a first row ``frames before bleaching``): ``rule``
        (`` (skipped)`` appended where skipped), ``molecules removed``, ``frames removed``,
        ``molecules left`` and ``frames left``.

    Raises
    ------
    BayespsfInputError
        A table without the columns it needs.

    See Also
    --------
    Rules : the settings.
    report_markdown : the report as markdown.
    find_molecules : makes both tables and applies this.

    Notes
    -----
    The rules run in the order of ``RULES`` (module docstring), each on what the previous
    ones left; frames after a molecule's bleaching step are never valid.
    """
    rules = (Rules() if rules is None else rules).for_psf(None)
    _require(molecules, MOLECULE_COLUMNS, "molecules")
    _require(frames, FRAME_COLUMNS, "frames")
    mol = molecules.copy()
    fr = frames.copy()
    mol["rejected_by"], fr["rejected_by"] = "", ""
    fr.loc[~fr["before_bleach"].astype(bool), "rejected_by"] = "after bleaching"
    report = [_row("frames before bleaching", mol, fr, 0, 0)]
    for rule in RULES:
        before_m, before_f = _alive(mol).sum(), _valid(fr, mol).sum()
        if rule not in rules.skip:
            _APPLY[rule](mol, fr, rules)
        removed_m = before_m - _alive(mol).sum()
        removed_f = before_f - _valid(fr, mol).sum()
        report.append(_row(rule, mol, fr, removed_m, removed_f, skipped=rule in rules.skip))
    mol["selected"] = mol["rejected_by"] == ""
    fr["valid"] = _valid(fr, mol)
    mol["valid_frames"] = (
        fr[fr["valid"]].groupby("molecule").size().reindex(mol["molecule"]).fillna(0).astype(int)
    ).to_numpy()
    table = pd.DataFrame(report)
    table.attrs = {}  # tables hold plain columns only
    return mol, fr, table


def _alive(mol):
    return mol["rejected_by"] == ""


def _valid(fr, mol):
    alive = fr["molecule"].isin(mol.loc[_alive(mol), "molecule"])
    return alive & (fr["rejected_by"] == "")


def _reject(mol, which, rule):
    mol.loc[which & _alive(mol), "rejected_by"] = rule


def _single_step(mol, fr, rules):
    _reject(mol, mol["steps"] != 1, "single_step")


def _no_drift(mol, fr, rules):
    z = np.maximum(
        np.abs(mol["drift_x"] / mol["drift_x_se"]), np.abs(mol["drift_y"] / mol["drift_y_se"])
    )
    _reject(mol, ~(z <= rules.drift_sigmas), "no_drift")  # NaN (too few frames) fails too


def _snr(mol, fr, rules):
    i0 = fr["peak"].to_numpy(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = i0 / np.sqrt(i0 + fr["background_var"].to_numpy(float))
    bad = ~(snr > rules.min_snr) & (fr["rejected_by"] == "").to_numpy()
    fr.loc[bad, "rejected_by"] = "snr"


def _photon_window(mol, fr, rules):
    valid = _valid(fr, mol)
    mean = fr[valid].groupby("molecule")["photons"].mean()
    ratio = fr["photons"] / fr["molecule"].map(mean)
    outside = valid & ~(np.abs(ratio - 1) <= rules.photon_tolerance)
    fr.loc[outside, "rejected_by"] = "photon_window"
    counts = fr[_valid(fr, mol)].groupby("molecule").size()
    enough = mol["molecule"].map(counts).fillna(0) >= rules.min_valid_frames
    _reject(mol, ~enough, "photon_window")


def _mean_widths(mol, fr):
    valid = fr[_valid(fr, mol)].groupby("molecule")[["s_x", "s_y"]].mean()
    return mol["molecule"].map(valid["s_x"]), mol["molecule"].map(valid["s_y"])


def _equal_widths(mol, fr, rules):
    sx, sy = _mean_widths(mol, fr)
    limit = np.maximum(rules.width_difference_nm, rules.width_difference_fraction * (sx + sy) / 2)
    _reject(mol, ~(np.abs(sx - sy) <= limit), "equal_widths")


def _width_range(mol, fr, rules):
    sx, sy = _mean_widths(mol, fr)
    inside = sx.between(rules.width_low, rules.width_high) & sy.between(
        rules.width_low, rules.width_high
    )
    _reject(mol, ~inside, "width_range")


_APPLY = {
    "single_step": _single_step,
    "no_drift": _no_drift,
    "snr": _snr,
    "photon_window": _photon_window,
    "equal_widths": _equal_widths,
    "width_range": _width_range,
}


def _row(rule, mol, fr, removed_m, removed_f, skipped=False):
    return {
        "rule": rule + (" (skipped)" if skipped else ""),
        "molecules removed": int(removed_m),
        "frames removed": int(removed_f),
        "molecules left": int(_alive(mol).sum()),
        "frames left": int(_valid(fr, mol).sum()),
    }


def report_markdown(report: pd.DataFrame, rules: Rules | None = None) -> str:
    """The selection report as markdown: the rules' settings, then the table in order."""
    rules = (Rules() if rules is None else rules).for_psf(None)
    used = [k for k, rule in SETTING_RULES.items() if rule not in rules.skip]  # the rules run
    settings = ", ".join(f"{k} = {getattr(rules, k)}" for k in used) or "none"
    skipped = f" Skipped: {', '.join(rules.skip)}." if rules.skip else ""
    return (
        "# Selection report\n\n"
        "The selection rules of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), applied in "
        "order, each to what the previous ones left (frames after a molecule's bleaching step "
        f"are never valid). Settings: {settings}.{skipped}\n\n"
        + report.to_markdown(index=False)
        + "\n"
    )


__all__ = ["FRAME_COLUMNS", "MOLECULE_COLUMNS", "RULES", "Rules", "report_markdown", "select"]
