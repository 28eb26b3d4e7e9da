"""Movies: reading, projecting and detecting on a large movie frame by frame, with its peak
memory.

Writes a 2 000-frame 512 x 512 uint16 movie (1 GiB; photon counts: a background of 100 photons
per pixel and 144 immobile spots of 300 photons per frame, SD 1.3 pixels, 40 pixels apart on a
grid; Poisson noise) with tifffile in a temporary directory (removed afterwards), in a separate
process so that writing it does not count in this process's peak memory; then opens it with
``bayespsf.movie.read_movie``, reads every frame in blocks of 64, projects the mean and the
median over all frames (default memory budget, 256 MiB), and detects the molecules on the mean
projection (``detect_movie``, a photon-counting camera, 100 nm pixels). Per step: time, time
per frame, the peak of Python's traced allocations (tracemalloc: NumPy arrays included, memory-
mapped file pages not) and the growth of the process's peak resident memory
(``resource.getrusage``: file pages mapped while a step runs included); each step is timed in a
first run and traced in a second (tracemalloc slows Python-level code). The file has just been
written, so it is read from the page cache: the times are those of a warm file, not of a disk.

    python benchmarks/movie.py            # full run, rewrites its section of README.md
    python benchmarks/movie.py --quick    # 100 frames of 128 x 128, prints only (the tests)
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import pandas as pd
import tifffile  # noqa: F401  (imported here, so that opening the movie is timed without it)
from _report import machine, publish

from bayespsf.cameras import Photon
from bayespsf.model import MIN_ROI, Model
from bayespsf.movie import detect_movie, project, read_movie

WRITE = """
import sys
import numpy as np
import tifffile

from bayespsf import psf

path, n, h, w = sys.argv[1], *map(int, sys.argv[2:])
rng = np.random.default_rng(13)
lam = np.full((h, w), 100.0)
for r in range(20, h - 20, 40):
    for c in range(20, w - 20, 40):
        spot = psf.expected_counts([0.0, 0.0, 130.0, 130.0, 300.0, 0.0], 15, 100.0)
        lam[r - 7 : r + 8, c - 7 : c + 8] += spot
frames = (rng.poisson(lam).astype(np.uint16) for _ in range(n))
tifffile.imwrite(path, frames, shape=(n, h, w), dtype=np.uint16, photometric="minisblack")
"""


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def _step(rows: list, name: str, n_frames: int, run):
    """Run one step twice: timed, with the growth of the peak RSS; then under tracemalloc
    (which slows Python-level code, such as walking the pages, many times) for its peak of
    traced allocations. Returns the first run's result."""
    before = _peak_rss_mb()
    start = time.perf_counter()
    result = run()
    seconds = time.perf_counter() - start
    grown = _peak_rss_mb() - before
    tracemalloc.start()
    run()
    traced = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    rows.append(
        {
            "step": name,
            "frames": n_frames,
            "seconds": seconds,
            "ms per frame": 1e3 * seconds / n_frames,
            "tracemalloc peak (MB)": traced / 1e6,
            "peak RSS growth (MB)": grown,
        }
    )
    return result


def run(quick: bool = False) -> tuple[pd.DataFrame, dict]:
    """The table of steps and the movie's description (frames, shape, size, peak RSS)."""
    n, h, w = (100, 128, 128) if quick else (2000, 512, 512)
    rows: list = []
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "movie.tif"
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", WRITE, str(path), str(n), str(h), str(w)], check=True)
        written = time.perf_counter() - start
        baseline = _peak_rss_mb()
        movie = _step(rows, "read_movie (open, check every page)", n, lambda: read_movie(path))
        _step(
            rows,
            "read every frame (blocks of 64)",
            n,
            lambda: sum(len(b) for _, b in movie.blocks(64)),
        )
        for kind in ("mean", "median"):
            _step(rows, f"project {kind}", n, lambda kind=kind: project(movie, kind))
        model = Model(MIN_ROI, 100.0, Photon())
        found = _step(
            rows,
            "detect_movie (mean projection, then detection)",
            n,
            lambda: detect_movie(movie, psf_sd=130.0, camera=model),
        )
        movie.close()
        info = {
            "movie": f"{n} frames of {h} x {w} uint16, {path.stat().st_size / 2**30:.3g} GiB",
            "written in (s)": written,
            "peak RSS before reading (MB)": baseline,
            "peak RSS after (MB)": _peak_rss_mb(),
            "spots": len(range(20, h - 20, 40)) * len(range(20, w - 20, 40)),
            "accepted candidates": int((found["status"] == "accepted").sum()),
        }
    return pd.DataFrame(rows), info


def markdown(table: pd.DataFrame, info: dict, command: str) -> str:
    fmt = {"index": False, "floatfmt": ".3g"}
    return (
        f"Movie: {info['movie']} (written by tifffile in {info['written in (s)']:.1f} s, in "
        "another process). Peak RSS of this process: "
        f"{info['peak RSS before reading (MB)']:.0f} MB after imports, "
        f"{info['peak RSS after (MB)']:.0f} MB at the end. Detection accepted "
        f"{info['accepted candidates']} candidates for {info['spots']} spots.\n\n"
        f"{table.to_markdown(**fmt)}\n\n"
        f"Command: `{command}` on {machine()}."
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small movie; print only")
    args = parser.parse_args(argv)
    table, info = run(quick=args.quick)
    command = "python benchmarks/movie.py" + (" --quick" if args.quick else "")
    publish("movie", markdown(table, info, command), args.quick)
    return table, info


if __name__ == "__main__":
    main()
