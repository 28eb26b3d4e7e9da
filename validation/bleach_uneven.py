"""Bleaching steps on uneven backgrounds: is the bleach frame found within one frame as often
on a ramp or an illumination profile as on a flat field, and how close is it to what the
per-frame signal allows?

Three fields, each a movie of immobile single-fluorophore molecules on an EMCCD (paper-movie's
camera: gain 200, readout 50 e-, offset 100 ADU, 12 e- per ADU, whole 16-bit ADU), drawn as
``detection_uneven.py`` draws them (its ``background`` and camera; the scene format declares no
uneven background): flat at 7 photons per pixel per frame, a ramp of 4 to 10 photons across the
columns, and a Gaussian illumination profile (10 at the centre, SD 133 pixels). Molecules sit
on a jittered grid about 30 pixels apart; each has N photons per frame log-uniform in 20-2000
(two decades: at the low end the per-frame step is 0.8 to 1.2 noise SDs of the PSF-weighted
photons on 10 to 4 photons per pixel, at the top 26 SDs of the lit frames' noise; N does not
follow the illumination) and bleaches at a time T uniform in [0, 1.25 x frames) frame times:
the frame ``floor(T)`` holds the fraction ``T - floor(T)`` of its photons, the bleach frame is
``ceil(T)`` (as ``simulate_movie``'s), and a molecule with ``ceil(T) >= frames`` does not
bleach in the movie. Each movie goes through ``find_molecules``' first two stages with its
defaults (``detect_movie`` with the camera, then ``molecules_over_time`` on the accepted
candidates, 25 x 25 ROIs, 15 x 15 centre; the frame fits and rules that follow do not change
``bleach_frame``). A candidate within 1.5 pixels of a molecule finds it.

Judged: the molecules that bleach in the movie and are found. The share whose bleach frame is
within +-1 frame of the truth is reported with its binomial SE, per field and in bins of the
per-frame step's signal-to-noise ratio ``N / sigma``, ``sigma`` the SD of the PSF-weighted
photons of one frame at the molecule's true background (the camera law, closed form). Beside
it, a yardstick independent of bayespsf's step finder: the share a textbook estimator reaches
on the same molecules when told there is exactly one step, least-squares placement of one split
(two free levels) on a Gaussian trace with the molecule's N, T and per-frame noise, 100 draws a
molecule. Molecules that do not bleach in the movie and show a step count as false steps (such
a molecule would pass the ``single_step`` rule). Every miss is listed with its N, its
background, its SNR, the true bleach frame and what the step finder returned.

    python validation/bleach_uneven.py          # 20 movies a field, 256 x 256, 240 frames
    python validation/bleach_uneven.py --quick  # 1 movie a field, 128 x 128, 120 frames
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).parent))
from _common import finish, saved_figure, study
from detection_uneven import CAMERA, S0, SIDE, A, background, molecules

from bayespsf import psf
from bayespsf.movie import detect_movie, molecules_over_time, read_movie

FIELDS = ("flat", "ramp", "gaussian")
N_RANGE = (20.0, 2000.0)  # photons per frame, log-uniform
LATE = 1.25  # bleach times uniform in [0, LATE x frames)
ROI, FIT = 25, 15  # find_molecules' defaults: the periphery outside FIT gives the background
BINS = (0.0, 1.0, 1.5, 2.0, 3.0, 5.0, np.inf)  # per-frame step SNR
ORACLE_DRAWS = 100


def frame_noise(n: np.ndarray, b: np.ndarray) -> np.ndarray:
    """SD (photons) of the PSF-weighted photons of one frame, at N photons on b per pixel: the
    camera law's variance of each pixel of the FIT x FIT centre weighted by the matched
    filter ``g / sum g^2``, plus the weights' sum times the SE of the periphery's mean."""
    g = psf.expected_counts([0.0, 0.0, S0, S0, 1.0, 0.0], FIT, A).ravel()
    w = g / (g @ g)
    per_adu = CAMERA.photons_per_adu()[0]
    n, b = np.broadcast_arrays(np.asarray(n, float), np.asarray(b, float))
    pixel = CAMERA.variance(b[..., None] + n[..., None] * g) * per_adu**2
    ring = ROI**2 - FIT**2
    return np.sqrt((w**2 * pixel).sum(-1) + w.sum() ** 2 * CAMERA.variance(b) * per_adu**2 / ring)


def oracle(n: float, b: float, t: float, frames: int, rng) -> float:
    """Share of ``ORACLE_DRAWS`` Gaussian traces (level ``n * clip(t - f, 0, 1)``, noise
    ``frame_noise`` at that level) whose least-squares single split lies within one frame of
    ``ceil(t)``: the split k minimises the two levels' summed squares over k = 1..frames-1."""
    level = n * np.clip(t - np.arange(frames), 0.0, 1.0)
    y = level + frame_noise(level, b) * rng.standard_normal((ORACLE_DRAWS, frames))
    s = np.cumsum(y, axis=1)
    k = np.arange(1, frames)
    left, total = s[:, :-1], s[:, -1:]
    fit = left**2 / k + (total - left) ** 2 / (frames - k)  # SSE = const - fit
    split = k[np.argmax(fit, axis=1)]
    return float(np.mean(np.abs(split - np.ceil(t)) <= 1))


def one_movie(field: str, seed: int, size: int, frames: int) -> list[dict]:
    """One movie of ``field``: one row per molecule with its truth and what was found."""
    rng = np.random.default_rng([seed, FIELDS.index(field), 2])
    shape = (size, size)
    truth = molecules(shape, rng)
    truth["N"] = np.exp(rng.uniform(*np.log(N_RANGE), len(truth)))
    truth["T"] = rng.uniform(0.0, LATE * frames, len(truth))
    on = np.clip(truth["T"].to_numpy()[:, None] - np.arange(frames), 0.0, 1.0)  # (M, frames)
    flat = background(field, shape)
    h = SIDE // 2
    spots = []
    for x, y, n in truth[["x", "y", "N"]].to_numpy():
        c, r = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        spot = psf.expected_counts([(x - c) * A, (y - r) * A, S0, S0, n, 0.0], SIDE, A)
        spots.append((slice(r - h, r + h + 1), slice(c - h, c + h + 1), spot))
    movie = np.empty((frames, *shape), dtype=np.uint16)
    for f in range(frames):
        expected = flat.copy()
        for (rows, cols, spot), fraction in zip(spots, on[:, f], strict=True):
            expected[rows, cols] += fraction * spot
        movie[f] = np.clip(np.round(CAMERA.sample(expected[None], rng)[0]), 0, 65535)
    with tempfile.TemporaryDirectory() as folder:
        np.save(Path(folder) / "m.npy", movie)
        data = read_movie(Path(folder) / "m.npy")
        candidates = detect_movie(data, psf_sd=S0, pixel_size=A, camera=CAMERA, roi=ROI)
        accepted = candidates[candidates["status"] == "accepted"].reset_index(drop=True)
        found, _ = molecules_over_time(data, accepted, CAMERA, s0=S0, pixel_size=A, roi=ROI)
    distance = np.hypot(
        found["x"].to_numpy()[:, None] - truth["x"].to_numpy(),
        found["y"].to_numpy()[:, None] - truth["y"].to_numpy(),
    )
    b = flat[np.round(truth["y"]).astype(int), np.round(truth["x"]).astype(int)]
    rows = []
    for k, (n, t) in enumerate(truth[["N", "T"]].to_numpy()):
        near = np.flatnonzero(distance[:, k] < 1.5)
        bleach = int(np.ceil(t)) if np.ceil(t) < frames else None
        row = {"field": field, "seed": seed, "N": n, "b": b[k], "true bleach frame": bleach}
        row["SNR"] = n / frame_noise(0.0, b[k])
        row["found"] = len(near) > 0
        row["steps"], row["bleach frame"] = -1, None
        if len(near):
            got = found.iloc[near[0]]
            row["steps"] = int(got["steps"])
            row["bleach frame"] = None if pd.isna(got["bleach_frame"]) else int(got["bleach_frame"])
        judged = row["found"] and bleach is not None
        row["oracle"] = oracle(n, b[k], t, frames, rng) if judged else np.nan
        rows.append(row)
    return rows


def judge(molecules: pd.DataFrame) -> pd.DataFrame:
    """The judged molecules (found, bleaching in the movie) with ``within`` (+-1 frame)."""
    judged = molecules[molecules["found"] & molecules["true bleach frame"].notna()].copy()
    error = (judged["bleach frame"].astype(float) - judged["true bleach frame"].astype(float)).abs()
    judged["within"] = (error <= 1).to_numpy()  # NaN (no bleach frame) is a miss
    return judged


def share(within: pd.Series) -> tuple[float, float]:
    p = float(within.mean()) if len(within) else np.nan
    return p, float(np.sqrt(p * (1 - p) / len(within))) if len(within) else np.nan


def summary(molecules: pd.DataFrame) -> pd.DataFrame:
    """Per field: the share within +-1 frame (binomial SE), the yardstick, the misses."""
    judged = judge(molecules)
    rows = []
    for field in FIELDS:
        one, all_ = judged[judged["field"] == field], molecules[molecules["field"] == field]
        p, se = share(one["within"])
        stays = all_[all_["found"] & all_["true bleach frame"].isna()]
        misses = one[~one["within"]]
        rows.append(
            {
                "field": field,
                "movies": all_["seed"].nunique(),
                "molecules": len(all_),
                "judged": len(one),
                "within 1 frame": p,
                "SE": se,
                "yardstick (one known step)": float(one["oracle"].mean()),
                "misses: no step": int((misses["steps"] == 0).sum()),
                "misses: one step": int((misses["steps"] == 1).sum()),
                "misses: more steps": int((misses["steps"] > 1).sum()),
                "not bleaching, with a step": f"{int((stays['steps'] > 0).sum())} of {len(stays)}",
            }
        )
    return pd.DataFrame(rows)


def by_snr(molecules: pd.DataFrame) -> pd.DataFrame:
    """The share within +-1 frame and the yardstick per SNR bin and field."""
    judged = judge(molecules)
    judged["bin"] = pd.cut(judged["SNR"], BINS, right=False)
    rows = []
    for (snr, field), group in judged.groupby(["bin", "field"], observed=True):
        p, se = share(group["within"])
        rows.append(
            {"SNR": f"{snr.left:g}-{snr.right:g}", "field": field, "judged": len(group)}
            | {"within 1 frame": p, "SE": se, "yardstick": float(group["oracle"].mean())}
            | {"_order": (snr.left, FIELDS.index(field))}
        )
    return pd.DataFrame(rows).sort_values("_order").drop(columns="_order")


def figure(bins: pd.DataFrame, path: Path) -> None:
    with saved_figure(path, (6, 3)) as ax:
        names = list(dict.fromkeys(bins["SNR"]))
        for k, field in enumerate(FIELDS):
            one = bins[bins["field"] == field]
            x = np.array([names.index(s) for s in one["SNR"]]) + 0.1 * (k - 1)
            ax.errorbar(x, one["within 1 frame"], yerr=2 * one["SE"], fmt="o", label=field)
            ax.plot(x, one["yardstick"], "x", color="grey")
        ax.axhline(0.9, color="grey", lw=1, ls="--")
        ax.set_xticks(range(len(names)), names, fontsize=7)
        ax.set_xlabel("per-frame step SNR N / sigma")
        ax.set_ylabel("within 1 frame (x: one known step)")
        ax.legend(fontsize=7)


def main(argv=None):
    args, started, stem = study(__doc__, argv, "bleach_uneven", posteriors=False)
    movies, size, frames = (1, 128, 120) if args.quick else (20, 256, 240)
    molecules = pd.DataFrame(
        [
            row
            for field in FIELDS
            for seed in range(movies)
            for row in one_movie(field, seed, size, frames)
        ]
    )
    table, bins = summary(molecules), by_snr(molecules)
    judged = judge(molecules)
    misses = judged[~judged["within"]].sort_values(["field", "SNR"])
    columns = ["field", "seed", "N", "b", "SNR", "true bleach frame", "steps", "bleach frame"]
    figure(bins, args.out / f"{stem}.png")
    fmt = {"index": False, "floatfmt": ".3g"}
    title = f"{movies} movies a field, {size} x {size} pixels, {frames} frames"
    text = (
        f"### Bleaching steps on uneven backgrounds ({title})\n\n{table.to_markdown(**fmt)}"
        f"\n\nBy the per-frame step's SNR:\n\n{bins.to_markdown(**fmt)}"
        f"\n\nMisses:\n\n{misses[columns].to_markdown(**fmt)}"
        f"\n\nFigure: [{stem}.png]({stem}.png)."
    )
    readme = (
        f"{title}; N log-uniform in {N_RANGE[0]:g}-{N_RANGE[1]:g} photons per frame: the share "
        "of found, bleaching molecules whose bleach frame is within +-1 frame (binomial SE), "
        "beside a textbook estimator told there is one step.\n\n"
        f"{table.to_markdown(**fmt)}\n\n{bins.to_markdown(**fmt)}\n\n"
        f"![within one frame by SNR](results/{stem}.png)"
    )
    return finish(args, "bleach_uneven", table, text, started, readme)


if __name__ == "__main__":
    main()
