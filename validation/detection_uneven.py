"""Detection on uneven backgrounds: does the stated false-positive rate per image hold, and are
the molecules found, when the background varies across the field as in every TIRF image?

Five fields, each a movie of immobile molecules on an EMCCD (paper-movie's camera: gain 200,
readout 50 e-, offset 100 ADU, 12 e- per ADU, whole 16-bit ADU) detected as ``bayespsf
detect`` does (``detect_movie`` on the mean projection with the camera: the threshold from the
camera law's tail at each pixel's local background):

* flat: 7 photons per pixel per frame;
* ramp: 4 to 10 photons per pixel across the columns (2.5 x);
* gaussian: an illumination profile of SD 133 pixels, 10 photons at the centre falling to 4
  in the corners of 256 x 256 pixels;
* narrow beam: a profile of SD 60 pixels (a quarter of the field), 25 photons over a floor of
  3 at its peak, off centre (at 40% of the rows and 60% of the columns): it bends within the
  background's 75-pixel window, where a quadratic surface is up to 0.21 photons off (the
  quartic 0.01);
* fixed pattern: 7 photons per pixel on the same EMCCD whose offset differs from pixel to
  pixel (100 ADU, SD 3 ADU between pixels: 0.18 photons, a variance of about a quarter of
  the mean projection's noise variance at 100 frames), while the detector is given the
  camera's one offset of 100 ADU (the movie path converts with one offset and gain).

The scene format declares no uneven background, so each movie is drawn here with the camera's
own law (``Camera.sample``) from its expected photons: the background plus, per molecule, the
pixel-integrated Gaussian (s0 = 120 nm, 79 nm pixels) with N photons per frame, log-uniform in
15-1500 (the faintest near the threshold at 10 photons per pixel), on a jittered grid (>= 13
pixels from the edges, about 30 apart). A candidate (any status) within 1.5 pixels of a
molecule finds it; any other is false. Recall is the share of molecules found; its matched-
filter expectation is ``mean Φ(E[T] - t)`` over the molecules, ``E[T] = N ||g|| / sqrt(v)``
with ``v`` the camera law's variance at the true background and ``t`` the median threshold
(for a spot on a pixel's centre: an upper value, a spot between pixels scores a little less).
Detected at the default 0.01 false candidates per image, and at 1 and 10 per image, where a
count over the movies can confirm the rate and not only bound it (Poisson SE).

    python validation/detection_uneven.py          # 25 movies a field, 256 x 256, 100 frames
    python validation/detection_uneven.py --quick  # 1 movie a field, 128 x 128, 100 frames
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study

from bayespsf import psf
from bayespsf.cameras import EMCCD
from bayespsf.movie import detect_movie, read_movie

FIELDS = ("flat", "ramp", "gaussian", "narrow beam", "fixed pattern")
RATES = (0.01, 1.0, 10.0)
A, S0 = 79.0, 120.0  # pixel size and PSF SD (nm), paper-movie's
CAMERA = EMCCD(200.0, 50.0, 100.0, 12.0)
PATTERN_SD = 3.0  # ADU: the fixed-pattern offset's SD between pixels
SIDE = 15  # the spot's window (the detector's template: 2 ceil(4 s0 / a) + 1)


def background(field: str, shape: tuple[int, int]) -> np.ndarray:
    """Expected background photons per pixel per frame."""
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(np.float64)
    if field == "ramp":
        return 4.0 + 6.0 * cols / (shape[1] - 1)
    if field == "gaussian":  # 10 at the centre, 4 at 127.5 * sqrt(2) (256 x 256's corners)
        r2 = (rows - (shape[0] - 1) / 2) ** 2 + (cols - (shape[1] - 1) / 2) ** 2
        return 10.0 * np.exp(np.log(0.4) * r2 / (2 * 127.5**2))
    if field == "narrow beam":  # SD a quarter of the field, peak off centre
        r2 = (rows - 0.4 * shape[0]) ** 2 + (cols - 0.6 * shape[1]) ** 2
        return 3.0 + 25.0 * np.exp(-r2 / (2 * (shape[0] / 4) ** 2))
    return np.full(shape, 7.0)


def offset_pattern(field: str, shape: tuple[int, int], rng: np.random.Generator):
    """The camera's offset less its declared 100 ADU, pixel by pixel (ADU)."""
    if field != "fixed pattern":
        return np.zeros(shape)
    return PATTERN_SD * rng.standard_normal(shape)


def molecules(shape: tuple[int, int], rng: np.random.Generator) -> pd.DataFrame:
    """Positions on a grid about 30 pixels apart, jittered by up to 3 pixels, and N."""
    ys, xs = (np.linspace(16.0, n - 17.0, max(2, round((n - 32) / 30) + 1)) for n in shape)
    x, y = (v.ravel() for v in np.meshgrid(xs, ys))
    x, y = x + rng.uniform(-3, 3, x.size), y + rng.uniform(-3, 3, y.size)
    photons = np.exp(rng.uniform(np.log(15.0), np.log(1500.0), x.size))
    return pd.DataFrame({"x": x, "y": y, "N": photons})


def expected_photons(field: str, shape, truth: pd.DataFrame) -> np.ndarray:
    """The background plus every molecule's pixel-integrated Gaussian, per frame."""
    image = background(field, shape)
    h = SIDE // 2
    for x, y, n in truth[["x", "y", "N"]].to_numpy():
        c, r = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        spot = psf.expected_counts([(x - c) * A, (y - r) * A, S0, S0, n, 0.0], SIDE, A)
        image[r - h : r + h + 1, c - h : c + h + 1] += spot
    return image


def one_movie(field: str, seed: int, size: int, frames: int) -> list[dict]:
    """One movie of ``field`` detected at each stated rate: one row per rate."""
    rng = np.random.default_rng([seed, FIELDS.index(field)])
    shape = (size, size)
    truth = molecules(shape, rng)
    pattern = offset_pattern(field, shape, rng)
    expected = expected_photons(field, shape, truth)
    movie = np.empty((frames, *shape), dtype=np.uint16)
    for f in range(frames):
        counts = CAMERA.sample(expected[None], rng)[0] + pattern
        movie[f] = np.clip(np.round(counts), 0, 65535)
    # each molecule's matched-filter score E[T] = N ||g|| / sqrt(v) on its pixel's centre, v
    # the mean projection's variance at its background (photons²), the pattern's included
    g = psf.expected_counts([0.0, 0.0, S0, S0, 1.0, 0.0], SIDE, A)
    r, c = np.round(truth["y"]).astype(int), np.round(truth["x"]).astype(int)
    per_adu = 12.0 / 200.0
    variance = CAMERA.variance(background(field, shape)[r, c]) / frames + PATTERN_SD**2 * (
        field == "fixed pattern"
    )
    expected_score = truth["N"].to_numpy() * np.sqrt((g**2).sum() / variance) / per_adu
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        np.save(Path(folder) / "m.npy", movie)
        for rate in RATES:
            table = detect_movie(
                read_movie(Path(folder) / "m.npy"),
                psf_sd=S0,
                pixel_size=A,
                camera=CAMERA,
                false_positives=rate,
            )
            distance = np.hypot(
                table["x"].to_numpy()[:, None] - truth["x"].to_numpy(),
                table["y"].to_numpy()[:, None] - truth["y"].to_numpy(),
            )
            near = distance < 1.5
            t = table.attrs["detection"]["threshold"]
            rows.append(
                {
                    "field": field,
                    "seed": seed,
                    "stated per image": rate,
                    "molecules": len(truth),
                    "found": int(near.any(axis=0).sum()),
                    "expected found": float(stats.norm.cdf(expected_score - t).sum()),
                    "false": int((~near.any(axis=1)).sum()),
                    "false accepted": int(
                        (~near.any(axis=1) & (table["status"] == "accepted").to_numpy()).sum()
                    ),
                }
            )
    return rows


def summary(movies: pd.DataFrame) -> pd.DataFrame:
    """Per field and stated rate: false candidates per image (Poisson SE), recall."""
    rows = []
    for (rate, field), group in movies.groupby(["stated per image", "field"], sort=False):
        n = len(group)
        false = group["false"].sum()
        rows.append(
            {
                "stated per image": rate,
                "field": field,
                "movies": n,
                "false per image": false / n,
                "SE": np.sqrt(false) / n,
                "false / stated": false / n / rate,
                "false accepted per image": group["false accepted"].sum() / n,
                "recall": group["found"].sum() / group["molecules"].sum(),
                "recall, worst movie": (group["found"] / group["molecules"]).min(),
                "expected recall": group["expected found"].sum() / group["molecules"].sum(),
            }
        )
    return pd.DataFrame(rows)


def figure(table: pd.DataFrame, path: Path) -> None:
    """False candidates per image over the stated rate (2 SE bars), and recall, per field."""
    with saved_figure(path, (9, 3), columns=2) as (left, right):
        for k, (rate, group) in enumerate(table.groupby("stated per image")):
            x = np.arange(len(group)) + 0.15 * k
            ratio = group["false / stated"]
            error = 2 * group["SE"] / rate
            left.errorbar(x, ratio, yerr=error, fmt="o", label=f"stated {rate:g} per image")
            right.plot(x, group["recall"], "o", label=f"recall at {rate:g}")
            right.plot(x, group["expected recall"], "x", color="grey")
        names = list(dict.fromkeys(table["field"]))
        for ax in (left, right):
            ax.set_xticks(range(len(names)), names, fontsize=7)
            ax.legend(fontsize=7)
        left.axhline(1.0, color="grey", lw=1)
        left.axhline(2.0, color="grey", lw=1, ls="--")
        left.set_ylabel("false candidates / stated")
        right.axhline(0.95, color="grey", lw=1, ls="--")
        right.set_ylabel("recall (x: matched-filter expectation)")


def main(argv=None):
    args, started, stem = study(__doc__, argv, "detection_uneven", posteriors=False)
    movies_per_field, size, frames = (1, 128, 100) if args.quick else (25, 256, 100)
    movies = pd.DataFrame(
        [
            row
            for field in FIELDS
            for seed in range(movies_per_field)
            for row in one_movie(field, seed, size, frames)
        ]
    )
    table = summary(movies)
    figure(table, args.out / f"{stem}.png")
    fmt = {"index": False, "floatfmt": ".3g"}
    title = f"{movies_per_field} movies a field, {size} x {size} pixels, {frames} frames"
    text = (
        f"### Detection on uneven backgrounds ({title})\n\n{table.to_markdown(**fmt)}"
        f"\n\nPer movie:\n\n{movies.to_markdown(**fmt)}\n\nFigure: [{stem}.png]({stem}.png)."
    )
    readme = (
        f"{title}, {movies['molecules'].iloc[0]} molecules each: false candidates per image "
        "(any status; Poisson SE) against the stated rate, and the share of molecules found.\n\n"
        f"{table.to_markdown(**fmt)}\n\n![false candidates and recall](results/{stem}.png)"
    )
    return finish(args, "detection_uneven", table, text, started, readme)


if __name__ == "__main__":
    main()
