"""Real acquisitions from peers' source distributions (``tests/data/real/README.md``):
``bayespsf calibrate`` and ``bayespsf detect`` run on them as a user runs them, without a
camera file to start from, and compared with the peers' own results on the same pixels:
3D-DAOSTORM's (sdt-python) on a frame of beads, rapidSTORM's (locan) on dSTORM frames."""

from __future__ import annotations

import json
import math
import re
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tifffile
from scipy import optimize
from scipy.spatial.distance import cdist

from bayespsf import cli

DATA = Path(__file__).resolve().parents[1] / "data" / "real"
BEADS = DATA / "sdt_beads.tif"
DAOSTORM = DATA / "sdt_beads_daostorm_2d.csv"
DSTORM = DATA / "locan_dstorm.tif"
RAPIDSTORM = DATA / "locan_rapidstorm.txt"

# sdt-python states no pixel size for the beads: 160 nm is the value of its own examples
# (sdt/motion/__init__.py), an assumption. Positions are compared in pixels, where it enters
# only through the spot's SD in nm.
BEADS_PIXEL_NM = 160.0
# The beads' spot SD, which `calibrate` uses only to mask the spots out of the background:
# 3D-DAOSTORM's median SD, 1.05 pixel, at 160 nm. It must be stated (see the xfail below).
BEADS_PSF_SD_NM = 168.0
# rapidSTORM's pixel: its header's position range is 0 to 1.69545e-5 m = 127 x 133.5 nm over
# the 128-pixel frame (locan's own script says 133 nm; test_rapidstorm_reference_matches_the_frames
# tells the two apart).
RAPIDSTORM_PIXEL_NM = 133.5
# The dSTORM spots' SD: rapidSTORM's median FWHM (350 nm over x and y) / 2.355.
DSTORM_PSF_SD_NM = 150.0
# Two localisations are the same spot within 1 pixel, about the beads' SD (1.05 pixel).
MATCH_RADIUS_PX = 1.0

_RAPIDSTORM_FIELDS = {
    "Position-0-0": ("x_nm", "nanometer"),
    "Position-1-0": ("y_nm", "nanometer"),
    "ImageNumber-0-0": ("frame", "frame"),
    "Amplitude-0-0": ("amplitude", "A/D count"),
    "PSFWidth-0-0": ("fwhm_x_nm", "nanometer"),
    "PSFWidth-1-0": ("fwhm_y_nm", "nanometer"),
    "FitResidues-0-0": ("fit_residues", "dimensionless"),
    "LocalBackground-0-0": ("background", "A/D count"),
}
_ESTIMATES = re.compile(
    r"ADU per photon (?P<M>\S+) \(SE (?P<M_se>[^;]+);.*?offset (?P<offset>\S+) \+- "
    r"(?P<offset_se>\S+) ADU, readout (?P<readout>\S+) \+- (?P<readout_se>\S+) ADU"
)


def rapidstorm_reference(
    path: str | Path = RAPIDSTORM, pixel_size: float = RAPIDSTORM_PIXEL_NM
) -> pd.DataFrame:
    """rapidSTORM's localisations in camera pixels, picasso's convention.

    Parameters
    ----------
    path : str or Path
        A rapidSTORM localisation file whose first line declares its columns
        (``# <localizations>`` with one ``<field>`` per column), such as
        ``tests/data/real/locan_rapidstorm.txt``.
    pixel_size : float
        rapidSTORM's pixel size in nm (133.5 for that file).

    Returns
    -------
    pandas.DataFrame
        One row per localisation: ``frame`` (from 0, the TIFF's page), ``x``, ``y`` (pixels:
        the centre of column ``j`` is ``x = j``, of row ``i`` is ``y = i``; rapidSTORM puts
        pixel ``j``'s centre at ``j * pixel_size`` nm), ``x_nm``, ``y_nm``, ``amplitude``
        and ``background`` (ADU), ``fwhm_x_nm``, ``fwhm_y_nm`` and ``fit_residues``.

    Raises
    ------
    ValueError
        A header that declares a field or unit other than those of ``_RAPIDSTORM_FIELDS``.
    """
    path = Path(path)
    header = path.read_text().splitlines()[0].lstrip("#").strip()
    names = []
    for field in ET.fromstring(header).iter("field"):
        name, unit = _RAPIDSTORM_FIELDS.get(field.get("identifier"), (None, None))
        if name is None or field.get("unit") != unit:
            raise ValueError(
                f"{path}: field {field.get('identifier')!r} in {field.get('unit')!r} is not "
                "one rapidstorm_reference knows"
            )
        names.append(name)
    table = pd.read_csv(path, sep=r"\s+", comment="#", header=None, names=names)
    table["frame"] = table["frame"].astype(int)
    table["x"] = table["x_nm"] / pixel_size
    table["y"] = table["y_nm"] / pixel_size
    first = ["frame", "x", "y"]
    return table[first + [c for c in table.columns if c not in first]]


def _estimates(camera_file: Path) -> dict[str, float]:
    """The estimates and standard errors that ``calibrate`` writes in its file's comments."""
    found = _ESTIMATES.search(camera_file.read_text())
    assert found, camera_file.read_text()
    return {key: float(value) for key, value in found.groupdict().items()}


def _calibrate(out: Path, *args: str) -> Path:
    assert cli.main(["calibrate", *args, "--out", str(out)]) == 0
    return out


def _check_camera_file(path: Path, image: np.ndarray, kind: str, pixel_size: float) -> None:
    """What a camera file from spatial photon transfer must satisfy on the image it came from."""
    toml = tomllib.loads(path.read_text())
    camera = toml["camera"]
    assert camera["kind"] == kind and toml["geometry"]["pixel_size"] == pixel_size
    assert math.isfinite(camera["gain"]) and camera["gain"] > 0
    assert math.isfinite(camera["offset"])
    est = _estimates(path)
    assert all(math.isfinite(v) for v in est.values())
    assert est["M_se"] > 0 and est["offset_se"] > 0 and est["readout_se"] > 0
    # the file's numbers are the printed ones (printed to 6 significant digits)
    assert camera["offset"] == pytest.approx(est["offset"], rel=1e-5)
    assert "approximate" in path.read_text()  # 1 to 19 frames: it says so
    # Under the file's own law a pixel is offset + photons (>= 0) + readout noise, so at most
    # Phi(-3) = 0.13% of pixels lie below offset - 3 readout SDs; 0.5% leaves room for the
    # offset's standard error.
    low = float(np.mean(image < est["offset"] - 3.0 * est["readout"]))
    assert low <= 0.005, (low, est)
    assert est["offset"] < np.median(image)  # the background holds photons


@pytest.fixture(scope="module")
def beads_camera(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("beads") / "camera.toml"
    args = (str(BEADS), "--pixel-size", str(BEADS_PIXEL_NM), "--psf-sd", str(BEADS_PSF_SD_NM))
    return _calibrate(out, *args)


@pytest.fixture(scope="module")
def dstorm_camera(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("dstorm") / "camera.toml"
    # The camera is not stated; without its readout noise an EMCCD cannot be calibrated from
    # five frames (test_calibrate_dstorm_as_emccd_needs_the_readout), so excess 1 (CCD, sCMOS).
    args = ("--pixel-size", str(RAPIDSTORM_PIXEL_NM), "--psf-sd", str(DSTORM_PSF_SD_NM))
    return _calibrate(out, str(DSTORM), *args, "--kind", "scmos")


def test_calibrate_beads(beads_camera):
    image = tifffile.imread(BEADS)
    assert image.dtype == np.uint16 and image.shape == (121, 421)
    # measured: gain 12.76 ADU per photon (SE 1.4), offset 206.8 +- 5.5 ADU, readout
    # 16.6 +- 1.9 ADU; 0.057% of pixels below offset - 3 readout SDs
    _check_camera_file(beads_camera, image, "emccd", BEADS_PIXEL_NM)


def test_calibrate_dstorm(dstorm_camera):
    image = tifffile.imread(DSTORM)
    assert image.dtype == np.uint16 and image.shape == (5, 128, 128)
    # measured: gain 11.4 ADU per photon (SE 2.3), offset 502 +- 33 ADU, readout 15.8 +- 2.3
    # ADU; 0.033% of pixels below offset - 3 readout SDs
    _check_camera_file(dstorm_camera, image, "scmos", RAPIDSTORM_PIXEL_NM)


def test_calibrate_dstorm_as_emccd_needs_the_readout(tmp_path):
    out = tmp_path / "camera.toml"
    args = ["--pixel-size", str(RAPIDSTORM_PIXEL_NM), "--psf-sd", str(DSTORM_PSF_SD_NM)]
    with pytest.raises(SystemExit, match=r"--readout-sd.*--dark"):
        cli.main(["calibrate", str(DSTORM), *args, "--out", str(out)])
    assert not out.exists()


def test_calibrate_beads_estimates_the_spot_sd(tmp_path, capsys):
    """Without --psf-sd, calibrate estimates the SD from the frame (no camera yet: least
    squares on the image). 3D-DAOSTORM's fits read a median of 1.054 px = 168.6 nm; this
    estimate reads 146 nm (-13%): unweighted least squares weighs the bright core of a real
    bead's spot, which is narrower than a Gaussian through its wings (the camera-law fit of
    ``detect`` reads 168-176 nm). The estimate only masks spots out of the background here, so
    the test asks for 25%, and states the measured -13%."""
    args = [str(BEADS), "--pixel-size", str(BEADS_PIXEL_NM), "--out", str(tmp_path / "c.toml")]
    assert cli.main(["calibrate", *args]) == 0
    printed = capsys.readouterr().out
    sd = float(re.search(r"spot SD s0 = ([\d.]+) \+- ([\d.]+) nm, estimated", printed).group(1))
    daostorm = pd.read_csv(DAOSTORM)["sigma_x"].median() * BEADS_PIXEL_NM
    assert abs(sd / daostorm - 1.0) < 0.25
    assert tomllib.loads((tmp_path / "c.toml").read_text())["camera"]["gain"] > 0


def _one_to_one(reference: pd.DataFrame, found: pd.DataFrame, radius: float) -> np.ndarray:
    """Distances (pixels) of the reference rows matched one to one to ``found`` (least total
    distance, pairs within ``radius`` only)."""
    distance = cdist(reference[["x", "y"]], found[["x", "y"]])
    rows, cols = optimize.linear_sum_assignment(np.where(distance < radius, distance, 1e6))
    matched = distance[rows, cols]
    return matched[matched < radius]


def test_detect_beads_matches_daostorm(beads_camera, tmp_path):
    # The beads lie ~10 pixels apart with an SD of ~1 pixel: an 11 x 11 ROI (9 x 9 fitted);
    # the spot's SD is estimated from the data (measured 172.8 +- 3.7 nm from 30 spots).
    out = tmp_path / "detected"
    args = ["--camera", str(beads_camera), "--rules", "none", "--roi", "11", "--fit", "9"]
    assert cli.main(["detect", str(BEADS), *args, "--out", str(out)]) == 0
    molecules = pd.read_csv(out / "molecules.csv")
    frames = pd.read_csv(out / "frames.csv")
    accepted = molecules[molecules["rejected_by"].isna()]
    assert len(accepted) >= 20 and set(frames["molecule"]) == set(accepted["molecule"])
    # 3D-DAOSTORM's peaks whose peak pixel is where bayespsf's 11 x 11 ROI fits (5 pixels
    # from each edge): 62 of its 64.
    reference = pd.read_csv(DAOSTORM)
    height, width = tifffile.imread(BEADS).shape
    col, row = np.rint(reference["x"]), np.rint(reference["y"])
    interior = reference[(col >= 5) & (col < width - 5) & (row >= 5) & (row < height - 5)]
    assert len(interior) == 62
    # molecules.csv's x, y (the detection's sub-pixel peak) are the positions of every
    # candidate; frames.csv's x, y are the aperture centroids of accepted ones (median 0.11
    # pixel from 3D-DAOSTORM's) and the frame fits' positions are not written.
    distance = _one_to_one(interior, molecules, MATCH_RADIUS_PX)
    # measured: 59 of 62 matched, median distance 0.028 pixel (90th percentile 0.086); each
    # of the other 3 has another 3D-DAOSTORM peak 1.2 to 3.3 pixels away: pairs it separates
    # in its residual where the detection finds one spot
    assert len(distance) >= 0.85 * len(interior), len(distance)
    assert np.median(distance) <= 0.05, np.median(distance)


def _fitted_position(image: np.ndarray, row: int, col: int, half: int = 5):
    """(x, y) in pixels of a least-squares Gaussian plus a constant on the 11 x 11 window
    around (row, col): independent of bayespsf and of rapidSTORM."""
    window = image[row - half : row + half + 1, col - half : col + half + 1].astype(float)
    y, x = np.mgrid[-half : half + 1, -half : half + 1]
    back = float(np.median(window))

    def residual(p):
        height, x0, y0, sd, b = p
        return (
            height * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * sd**2)) + b - window
        ).ravel()

    fit = optimize.least_squares(residual, [window.max() - back, 0.0, 0.0, 1.2, back])
    assert fit.success
    return col + fit.x[1], row + fit.x[2]


def test_rapidstorm_reference_matches_the_frames():
    reference = rapidstorm_reference()
    assert len(reference) == 12 and reference["frame"].between(1, 29).all()
    frames = tifffile.imread(DSTORM)
    inside = reference[reference["frame"] < len(frames)]
    assert list(inside["frame"]) == [1, 3, 3, 4]
    for spot in inside.itertuples():
        x, y = _fitted_position(frames[spot.frame], round(spot.y), round(spot.x))
        # Two fits of the same pixels differ by far less than their 0.1-pixel tolerance
        # (measured <= 0.02 pixel); 133 nm instead of 133.5 moves x by 0.30-0.33 pixel, a
        # half-pixel convention by 0.5, a frame numbered from 1 the spot to an empty frame.
        assert abs(x - spot.x) < 0.1 and abs(y - spot.y) < 0.1, (spot, x, y)


def test_detect_dstorm_runs_and_reports(dstorm_camera, tmp_path):
    # A mean projection is not the mode for blinking emitters (--per-frame is); this checks
    # that the command runs on the frames and finds the two emitters rapidSTORM localises in
    # them (within 1 pixel: a projection of blinks, not a localisation).
    out = tmp_path / "detected"
    args = ["--camera", str(dstorm_camera), "--psf-sd", str(DSTORM_PSF_SD_NM), "--rules", "none"]
    assert cli.main(["detect", str(DSTORM), *args, "--out", str(out)]) == 0
    for name in ("candidates.csv", "molecules.csv", "frames.csv", "selection.md", "run.json"):
        assert (out / name).is_file()
    assert "Candidates detected:" in (out / "selection.md").read_text()
    molecules = pd.read_csv(out / "molecules.csv")
    reference = rapidstorm_reference()
    inside = reference[reference["frame"] < 5]
    nearest = cdist(inside[["x", "y"]], molecules[["x", "y"]]).min(axis=1)
    # measured: 0.03 to 0.22 pixel
    assert (nearest < MATCH_RADIUS_PX).all(), (nearest, molecules)


def test_detect_dstorm_without_psf_sd_names_the_fix(dstorm_camera, tmp_path):
    # Five frames of blinks hold too few isolated spots to estimate the spot's SD: the
    # refusal names the option that states it.
    args = ["--camera", str(dstorm_camera), "--rules", "none", "--out", str(tmp_path / "d")]
    with pytest.raises(SystemExit, match=r"cannot estimate the spot's SD.*--psf-sd"):
        cli.main(["detect", str(DSTORM), *args])


def test_analyze_per_frame_finds_rapidstorms_localisations(dstorm_camera, tmp_path):
    """``analyze --per-frame`` on the dSTORM frames: each of rapidSTORM's localisations in
    them has one of ours in the same frame, and the positions agree. rapidSTORM's are
    least-squares fits, ours posterior means under the calibrated sCMOS law; the tolerance,
    0.15 px (20 nm), is a few times the posterior SDs of these 1 000-5 000-photon spots."""
    out = tmp_path / "per-frame"
    args = ["--camera", str(dstorm_camera), "--psf-sd", str(DSTORM_PSF_SD_NM), "--per-frame"]
    # importance sampling: three dim, blurred spots that rapidSTORM does not report fail the
    # Laplace Student-t (k-hat) and are sampled from a t fitted to its weighted draws, where
    # they took the chain (2 600-4 500 steps, ~12 s each on 2 cores); a budget of one second
    # per chain keeps the test short should one need it
    args += ["--method", "importance", "--max-seconds", "1", "--workers", "1"]
    assert cli.main(["analyze", str(DSTORM), *args, "--out", str(out)]) == 0
    assert json.loads((out / "run.json").read_text())["run"]["max seconds"] == 1.0
    locs = pd.read_parquet(out / "locs.parquet")
    chains = locs[locs["method"] == "mcmc"]
    # which ROIs fail importance sampling is set by their seeds; how long a chain runs is the
    # machine's, so each chain converged or stopped on the budget (no timing is asserted)
    budget = chains["message"].str.contains("the 1 s budget ran out", regex=False)
    assert (budget | (chains["status"] == "converged")).all(), chains
    assert locs["why"].str.contains("a t fitted to the weighted draws").sum() >= 1
    reference = rapidstorm_reference()
    inside = reference[reference["frame"] < len(tifffile.imread(DSTORM))]
    assert len(inside) == 4
    for spot in inside.itertuples():
        here = locs[locs["frame"] == spot.frame]
        distance = np.hypot(here["x"] - spot.x, here["y"] - spot.y)
        nearest = here.iloc[int(np.argmin(distance.to_numpy()))]
        assert distance.min() < 0.15, (spot, here[["x", "y", "lpx", "lpy"]])
        assert nearest["status"] == "converged", nearest
