"""Simulated movies of a field of immobile molecules: exactly the effects the scene's
``[movie]`` table declares.

Shaped like the experiment of DeSantis, DeCenzo, Li & Wang, Opt. Express 18 (2010), section
"Data acquisition and selection": molecules in a TIRF field imaged frame after frame on an
EMCCD, each bleaching (streptavidin-Cy3 monomers in one step; molecules with two fluorophores
in two), optionally with stage drift (their selection rule 1), moving molecules, blinking and
dark frames for the camera's calibration.

Each frame is built as ROIs are (``bayespsf.simulate``): the expected photons of every pixel
are the pixel-integrated elliptical Gaussian of every emitting molecule (``bayespsf.psf``,
the model inference uses), computed in a window of +-6 SD around the molecule (the mass
outside, < 2e-9, is neglected) and added into the frame; the scene's photon statistics,
background law and camera law then act on the whole frame through the simulator's own effects
(``bayespsf.simulation.pipeline.detection_effects``, with the quantum efficiency's thinning where
declared). Dark frames are the camera law alone. Photons in the truth tables are in the
scene's ``camera.photon_unit``.

Time: frame ``f`` spans ``[f, f + 1)`` frame times. A fluorophore bleaches at an exponential
time ``T`` (``movie.bleach_mean``) and blinks as a continuous-time two-state Markov chain
(``movie.blink_on``, ``movie.blink_off``, started in its stationary state); its photons in a
frame are its mean photons times the fraction of the frame it was on and not yet bleached, so
the frame in which it bleaches holds a part of its photons and ``bleach_frame = ceil(T)`` is
the first frame without it. Positions are constant within a frame: drift and random walks
step between frames; frame 0 is at the placed positions.

Positions are camera pixels in picasso's convention (as its Localize writes them: the fitted
offset plus the box's integer centre, ``picasso.localize.locs_from_fits_gauss``, with the
Gaussian evaluated at integer grid points, ``picasso/gausslq.py``): the centre of column ``j``
is ``x = j`` and of row ``i`` is ``y = i``; ``x_nm = x * pixel_size``.

Reproducibility: every effect draws from its own stream,
``SeedSequence(seed, spawn_key=(stream, frame))``, so the same seed gives the same movie on
any machine, and declaring one effect does not change the draws of another.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from bayespsf import psf
from bayespsf.errors import BayespsfInputError
from bayespsf.scene import Scene, SceneError
from bayespsf.simulation import effects as fx
from bayespsf.simulation.movie_files import MOLECULE_COLUMNS, TRUTH_COLUMNS, _write
from bayespsf.simulation.pipeline import (
    axial_effects,
    camera_effects,
    detection_effects,
    scene_photon_label,
    truth_photon_factor,
)

WINDOW_SDS = 6.0  # the PSF window's half-side in SDs
_PLACE, _PHOTONS, _FLUOROPHORES, _BLEACH, _MOVING, _BLINK, _AXIAL = range(7)  # per movie
_NOISE, _JITTER, _WALK, _BLINKING, _DARK = range(10, 15)  # per-frame streams


def _rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed, spawn_key=key)))


def movie_settings(scene: Scene) -> dict:
    """The scene's ``[movie]`` table, checked against the rest of the scene.

    Raises ``SceneError`` naming the keys when the scene declares no movie, declares effects a
    movie cannot honour (photon-by-photon widths, the Airy PSF) or a blinking half declared.
    """
    if not isinstance(scene, Scene):
        raise BayespsfInputError(f"scene must be a bayespsf.Scene, got {type(scene).__name__}")
    if "movie" not in scene.to_dict():
        raise SceneError("the scene declares no [movie] table (e.g. the shipped paper-movie)")
    if scene.optics["psf"] != "gaussian":
        raise SceneError("optics.psf must be 'gaussian' in a movie scene (movies draw its image)")
    if scene.emitter["width_jitter"] > 0:
        raise SceneError(
            "emitter.width_jitter is not used by movies (photons are not binned one by one); "
            "remove it"
        )
    m = dict(scene.movie)
    if (m["blink_on"] > 0) != (m["blink_off"] > 0):
        raise SceneError(
            "movie.blink_on and movie.blink_off declare blinking together: give both > 0 or "
            f"neither (got {m['blink_on']:g} and {m['blink_off']:g})"
        )
    return m


@dataclass
class MovieTruth:
    """What ``simulate_movie`` made (with ``out``, ``truth``, ``frames`` and ``dark`` are None).

    Parameters
    ----------
    molecules : pandas.DataFrame
        One row per molecule, columns ``MOLECULE_COLUMNS`` (see ``molecule_table``).
    truth : pandas.DataFrame or None
        One row per molecule and frame: ``molecule frame x y photons on fluorophores_on
        photon_unit`` (``TRUTH_COLUMNS``; x, y in pixels).
    frames, dark : ndarray or None
        ``(frames, height, width)`` and ``(dark_frames, height, width)`` in ADU, dtype
        ``frame_dtype(scene)``.
    files : dict of str to Path
        With ``out``: ``movie``, ``molecules``, ``truth`` and (with dark frames) ``dark``.
    """

    molecules: pd.DataFrame
    truth: pd.DataFrame | None = None
    frames: np.ndarray | None = None
    dark: np.ndarray | None = None
    files: dict[str, Path] = field(default_factory=dict)


def place_molecules(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``(x, y)`` in camera pixels: ``movie.molecules`` positions uniform over the frame, one
    after another, each where its nearest pixel keeps ``movie.edge`` pixels from the border
    and ``movie.min_spacing`` (Chebyshev) from every nearest pixel placed before.

    A position is drawn uniformly up to 100 times, then uniformly over the pixels still free;
    when none is free the placement is impossible: ``SceneError`` naming the keys.
    """
    m = movie_settings(scene)
    h, w, edge, gap, n = m["height"], m["width"], m["edge"], m["min_spacing"], m["molecules"]
    free = np.zeros((h, w), bool)
    free[edge : h - edge, edge : w - edge] = True
    xy = np.empty((n, 2))
    for k in range(n):
        for _ in range(100):
            x, y = rng.uniform([-0.5, -0.5], [w - 0.5, h - 0.5])
            if free[_nearest(y), _nearest(x)]:
                break
        else:
            cells = np.flatnonzero(free)
            if cells.size == 0:
                raise SceneError(
                    f"cannot place movie.molecules = {n} molecules in {h} x {w} pixels "
                    f"(movie.height x movie.width) at least movie.min_spacing = {gap} pixels apart "
                    f"and movie.edge = {edge} pixels from the border: no room for molecule {k + 1}"
                    "; lower molecules, min_spacing or edge, or enlarge the frame"
                )
            row, col = np.divmod(cells[rng.integers(cells.size)], w)
            x, y = col + rng.uniform(-0.5, 0.5), row + rng.uniform(-0.5, 0.5)
        xy[k] = x, y
        r, c = _nearest(y), _nearest(x)
        free[max(r - gap + 1, 0) : r + gap, max(c - gap + 1, 0) : c + gap] = False
    return xy[:, 0], xy[:, 1]


def _nearest(v):
    """The nearest pixel of a position (halves rounded up, as ``bayespsf.movie.extract``)."""
    return np.floor(np.asarray(v) + 0.5).astype(np.int64)


@dataclass
class _Molecules:
    """Per-molecule constants and the state that evolves from frame to frame."""

    x: np.ndarray  # positions at frame 0, pixels
    y: np.ndarray
    photons: np.ndarray  # mean photons per frame of each fluorophore
    present: np.ndarray  # (n, 2) bool: the molecule carries this fluorophore
    bleach: np.ndarray  # (n, 2) bleaching time in frames (inf: none)
    moving: np.ndarray
    s_x: np.ndarray  # widths, nm: the emitter's, or those of each molecule's z ([axial])
    s_y: np.ndarray
    z: np.ndarray | None  # axial position, nm, where the scene declares [axial]
    on: np.ndarray  # (n, 2) blinking state
    next_switch: np.ndarray  # (n, 2) time of the next blinking switch (inf: none)
    walk: np.ndarray  # (2, n) random-walk displacement so far, nm

    @property
    def bleach_frame(self) -> np.ndarray:
        last = np.where(self.present, self.bleach, -np.inf).max(axis=1)
        return np.ceil(last)


def _draw_molecules(scene: Scene, seed: int) -> _Molecules:
    m, e = movie_settings(scene), scene.emitter
    n = m["molecules"]
    x, y = place_molecules(scene, _rng(seed, _PLACE))
    low, high = (m[k] or e["photons"] for k in ("photons_low", "photons_high"))
    photons = np.full(n, float(low))
    if low != high:  # log-uniform between the two
        photons = np.exp(_rng(seed, _PHOTONS).uniform(math.log(low), math.log(high), n))
    present = np.ones((n, 2), bool)
    present[:, 1] = False
    if m["two_fluorophores"] > 0:
        present[:, 1] = _rng(seed, _FLUOROPHORES).random(n) < m["two_fluorophores"]
    bleach = np.full((n, 2), np.inf)
    if m["bleach_mean"] > 0:
        bleach = _rng(seed, _BLEACH).exponential(m["bleach_mean"], (n, 2))
    moving = np.zeros(n, bool)
    if m["moving"] > 0:
        moving = _rng(seed, _MOVING).random(n) < m["moving"]
    on, next_switch = np.ones((n, 2), bool), np.full((n, 2), np.inf)
    if m["blink_on"] > 0:  # the stationary state, then exponential (memoryless) durations
        rng = _rng(seed, _BLINK)
        on = rng.random((n, 2)) < m["blink_on"] / (m["blink_on"] + m["blink_off"])
        next_switch = rng.exponential(np.where(on, m["blink_on"], m["blink_off"]))
    s_x, s_y, z = np.full(n, float(e["s0x"])), np.full(n, float(e["s0y"])), None
    if "axial" in scene.to_dict():  # one z per molecule, kept in every frame (immobile)
        batch = fx.Batch(n, 0, {"s_x": s_x, "s_y": s_y})
        for step in axial_effects(scene):
            step(batch, _rng(seed, _AXIAL))
        s_x, s_y, z = batch.truth["s_x"], batch.truth["s_y"], batch.truth["z"]
    return _Molecules(
        x, y, photons, present, bleach, moving, s_x, s_y, z, on, next_switch, np.zeros((2, n))
    )


def _emitting_fraction(mol: _Molecules, frame: int, m: dict, rng) -> np.ndarray:
    """(n, 2): the fraction of frame ``frame`` each fluorophore emits (on, not yet bleached),
    advancing the blinking chains to the frame's end."""
    start, end = float(frame), frame + 1.0
    stop = np.minimum(mol.bleach, end)
    now = np.full(mol.on.shape, start)
    emitting = np.zeros(mol.on.shape)
    while True:
        upto = np.minimum(mol.next_switch, end)
        emitting += np.where(
            mol.on, np.clip(np.minimum(upto, stop) - np.minimum(now, stop), 0, 1), 0
        )
        switch = mol.next_switch < end
        if not switch.any():
            return np.where(mol.present, emitting, 0.0)
        now = np.where(switch, mol.next_switch, end)
        mol.on = np.where(switch, ~mol.on, mol.on)
        means = np.where(mol.on, m["blink_on"], m["blink_off"])
        mol.next_switch = np.where(
            switch, mol.next_switch + rng.exponential(means), mol.next_switch
        )


def frame_dtype(scene: Scene) -> np.dtype:
    """uint16 when the camera guarantees whole counts within 16 bits (``camera.quantize`` and
    ``0 < camera.saturation <= 65535``), else float32."""
    cam = scene.camera
    if cam.get("quantize") and 0 < cam.get("saturation", 0) <= 65535:
        return np.dtype(np.uint16)
    return np.dtype(np.float32)


def _as_frame(counts: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    if dtype == np.uint16 and counts.min() < 0:
        raise BayespsfInputError(
            f"{what} has counts below 0 ADU, which a 16-bit file cannot hold: raise camera.offset"
        )
    return counts.astype(dtype)


def _expected_frame(x, y, n_photons, widths, scene: Scene, rng) -> tuple[np.ndarray, str]:
    """The signal of one frame: expected photons (Poisson statistics) or whole photoelectrons
    (fixed statistics, a multinomial over each molecule's window), and its stage."""
    m, e, a = scene.movie, scene.emitter, scene.geometry["pixel_size"]
    h, w = m["height"], m["width"]
    fixed = e["photon_statistics"] == "fixed"
    lit = n_photons > 0
    s_x, s_y = (w_[lit] for w_ in widths)
    half = math.ceil(WINDOW_SDS * max(s_x.max(initial=0.0), s_y.max(initial=0.0)) / a + 0.5)
    r, c = _nearest(y[lit]), _nearest(x[lit])
    k = r.size
    params = np.column_stack(
        [(x[lit] - c) * a, (y[lit] - r) * a, s_x, s_y, np.ones(k), np.zeros(k)]
    )
    window = psf.expected_counts(params, 2 * half + 1, a)
    offsets = np.arange(-half, half + 1)
    rows, cols = r[:, None] + offsets, c[:, None] + offsets
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]
    flat = rows[:, :, None] * w + cols[:, None, :]
    if fixed:
        p = np.where(inside, window, 0.0).reshape(k, -1)
        outside = np.clip(1.0 - p.sum(axis=1, keepdims=True), 0.0, 1.0)
        drawn = rng.multinomial(n_photons[lit].astype(np.int64), np.hstack([p, outside]))
        window = drawn[:, :-1].reshape(window.shape).astype(float)
    else:
        window = window * n_photons[lit][:, None, None]
    image = np.bincount(flat[inside], weights=window[inside], minlength=h * w).reshape(h, w)
    return (np.rint(image) if fixed else image), ("photoelectrons" if fixed else "expected")


def iter_movie(scene: Scene, seed: int) -> Iterator[tuple[np.ndarray, pd.DataFrame]]:
    """The frames of ``simulate_movie``, one at a time (memory: one frame and the molecules).

    Parameters
    ----------
    scene : Scene
        A scene with a ``[movie]`` table.
    seed : int
        Non-negative integer.

    Yields
    ------
    counts : ndarray, shape (height, width)
        The frame in ADU (float64).
    truth : pandas.DataFrame
        The frame's rows of ``MovieTruth.truth`` (``TRUTH_COLUMNS``).

    Raises
    ------
    SceneError
        If the scene declares no movie or effects a movie cannot honour.
    """
    m, e, a = movie_settings(scene), scene.emitter, scene.geometry["pixel_size"]
    _check_seed(seed)
    mol = _draw_molecules(scene, seed)
    n = mol.x.size
    ids = np.arange(n)
    unit, label = truth_photon_factor(scene), scene_photon_label(scene)
    for f in range(m["frames"]):
        fraction = _emitting_fraction(mol, f, m, _rng(seed, _BLINKING, f))
        n_photons = mol.photons * fraction.sum(axis=1)
        if e["photon_jitter"] > 0:
            j = e["photon_jitter"]
            n_photons = n_photons * _rng(seed, _JITTER, f).uniform(1 - j, 1 + j, n)
        if e["photon_statistics"] == "fixed":
            n_photons = np.rint(n_photons)
        if f > 0 and mol.moving.any():
            steps = _rng(seed, _WALK, f).normal(0.0, m["moving_step"], (2, int(mol.moving.sum())))
            mol.walk[:, mol.moving] += steps
        x = mol.x + (m["drift_x"] * f + mol.walk[0]) / a
        y = mol.y + (m["drift_y"] * f + mol.walk[1]) / a
        rng = _rng(seed, _NOISE, f)
        image, stage = _expected_frame(x, y, n_photons, (mol.s_x, mol.s_y), scene, rng)
        batch = fx.Batch(n=1, roi=0, image=image[None], stage=stage)
        for step in detection_effects(scene, stage):
            step(batch, rng)
        on = (fraction > 0).sum(axis=1)
        truth = {
            "molecule": ids,
            "frame": np.full(n, f),
            "x": x,
            "y": y,
            "photons": n_photons * unit,
            "on": on > 0,
            "fluorophores_on": on,
            "photon_unit": label,
        }
        yield batch.image[0], pd.DataFrame(truth, columns=list(TRUTH_COLUMNS))


def iter_dark_frames(scene: Scene, seed: int) -> Iterator[np.ndarray]:
    """Yield the ``movie.dark_frames`` dark frames ``(height, width)`` in ADU: no light, so
    no signal and no background photons, only the camera law (clock-induced charge, the
    register, readout, offset, ADC)."""
    m = movie_settings(scene)
    _check_seed(seed)
    steps = camera_effects(scene.camera)
    for k in range(m["dark_frames"]):
        rng = _rng(seed, _DARK, k)
        zeros = np.zeros((1, m["height"], m["width"]), np.int64)
        batch = fx.Batch(n=1, roi=0, image=zeros, stage="photoelectrons")
        for step in steps:
            step(batch, rng)
        yield batch.image[0]


def molecule_table(scene: Scene, seed: int) -> pd.DataFrame:
    """One row per molecule (``MOLECULE_COLUMNS``): position at frame 0 (pixels, picasso's
    convention, and nm from the centre of pixel (0, 0)), widths (nm; where the scene declares
    ``[axial]``, those of the molecule's ``z``, a column before them), mean photons per frame
    of each fluorophore, fluorophores, the first frame after the last bleaching step (empty
    if it is not within the movie) and whether it moves (random walk)."""
    m, a = movie_settings(scene), scene.geometry["pixel_size"]
    _check_seed(seed)
    mol = _draw_molecules(scene, seed)
    last = mol.bleach_frame
    bleach = pd.Series(np.where(last < m["frames"], last, np.nan)).astype("Int64")
    table = pd.DataFrame(
        {
            "molecule": np.arange(mol.x.size),
            "x": mol.x,
            "y": mol.y,
            "x_nm": mol.x * a,
            "y_nm": mol.y * a,
            "s_x": mol.s_x,
            "s_y": mol.s_y,
            "photons": mol.photons * truth_photon_factor(scene),
            "fluorophores": mol.present.sum(axis=1),
            "bleach_frame": bleach,
            "moving": mol.moving,
            "photon_unit": scene_photon_label(scene),
        },
        columns=list(MOLECULE_COLUMNS),
    )
    if mol.z is not None:
        table.insert(table.columns.get_loc("s_x"), "z", mol.z)
    return table


def simulate_movie(scene: Scene, seed: int, out: str | Path | None = None) -> MovieTruth:
    """Simulate the movie a scene's ``[movie]`` table declares.

    Parameters
    ----------
    scene : Scene
        A scene with a ``[movie]`` table (e.g. ``bayespsf.load_scene("paper-movie")``).
    seed : int
        Non-negative integer; the same seed gives the same movie.
    out : str or Path, optional
        A path stem. When given, the movie is written frame by frame (one frame in memory):
        ``STEM.ome.tif`` (one page per frame, ``frame_dtype(scene)``, OME ``PhysicalSizeX/Y``
        in µm and ``TimeIncrement`` = ``movie.exposure`` in s when declared),
        ``STEM.molecules.csv``, ``STEM.truth.csv`` and, when ``movie.dark_frames`` > 0,
        ``STEM.dark.ome.tif``.

    Returns
    -------
    MovieTruth
        The molecule table, and the frames, dark frames and truth table (in memory without
        ``out``; on disk, named in ``files``, with it).

    Raises
    ------
    SceneError
        If the scene declares no ``[movie]``, declares effects a movie cannot honour
        (``emitter.width_jitter``, the Airy PSF, half a blinking), or its molecules do not fit.
    BayespsfInputError
        If ``seed`` is not an integer >= 0, or counts below 0 ADU go to a 16-bit file.

    See Also
    --------
    iter_movie : the frames one at a time.
    simulate : single ROIs of a scene.

    Examples
    --------
    >>> from bayespsf import load_scene, simulate_movie
    >>> scene = load_scene("paper-movie").replace(
    ...     movie={"frames": 5, "height": 64, "width": 64, "molecules": 3}
    ... )
    >>> movie = simulate_movie(scene, seed=1)
    >>> movie.frames.shape, movie.dark.shape, len(movie.molecules)
    ((5, 64, 64), (20, 64, 64), 3)
    """
    molecules = molecule_table(scene, seed)
    dtype = frame_dtype(scene)
    frames = (
        (_as_frame(c, dtype, f"frame {f}"), t) for f, (c, t) in enumerate(iter_movie(scene, seed))
    )
    dark = (
        _as_frame(c, dtype, f"dark frame {k}") for k, c in enumerate(iter_dark_frames(scene, seed))
    )
    if out is None:
        pairs = list(frames)
        m = scene.movie
        empty = np.empty((0, m["height"], m["width"]), dtype)
        return MovieTruth(
            molecules,
            pd.concat([t for _, t in pairs], ignore_index=True),
            np.stack([c for c, _ in pairs]),
            np.stack(list(dark)) if m["dark_frames"] else empty,
        )
    return MovieTruth(molecules, files=_write(scene, Path(out), molecules, frames, dark, dtype))


def match_truth(
    candidates: pd.DataFrame,
    molecules: pd.DataFrame,
    reach: float = 1.5,
    moving_reach: float = 10.0,
) -> np.ndarray:
    """For each candidate, the row of the true molecule it found, or -1.

    Parameters
    ----------
    candidates : pandas.DataFrame
        Columns ``x``, ``y`` in camera pixels.
    molecules : pandas.DataFrame
        A ``MovieTruth.molecules`` table (``x``, ``y``, ``moving``).
    reach : float, optional
        Largest Chebyshev distance in pixels to a molecule's frame-0 position.
    moving_reach : float, optional
        The same for a moving molecule, whose random walk smears its spot over the mean
        projection.

    Returns
    -------
    ndarray of int, shape (len(candidates),)
        Row of ``molecules`` of the nearest molecule within reach, or -1.
    """
    c = candidates[["x", "y"]].to_numpy(float)
    t = molecules[["x", "y"]].to_numpy(float)
    distance = np.max(np.abs(c[:, None, :] - t[None, :, :]), axis=-1)
    limit = np.where(molecules["moving"].to_numpy(bool), moving_reach, reach)
    near = distance <= limit[None, :]
    nearest = np.where(near, distance, np.inf).argmin(axis=1)
    return np.where(near.any(axis=1), nearest, -1)


def _check_seed(seed) -> None:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise BayespsfInputError(f"seed must be an integer >= 0, got {seed!r}")
