"""Simulator throughput and memory for every shipped scene.

Images per second for each shipped scene at 15x15 and 19x19 pixels, as a ratio to the ideal
photon-counting scene at the same size in the same run, and the peak traced memory of a run of
10^5 images (5 000 for the photon-by-photon paper-fig2) beside the size of its output array.

    python benchmarks/simulate.py            # full run, rewrites its section of README.md
    python benchmarks/simulate.py --quick    # small and fast, prints only
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import pandas as pd

from bayespsf import load_scene, shipped_scenes, simulate
from bayespsf._runtime import best_time

SIZES = (15, 19)


def run(quick: bool) -> pd.DataFrame:
    n = 2_000 if quick else 100_000
    repeat = 1 if quick else 3
    rows = []
    for roi in SIZES:
        for name in shipped_scenes():
            scene = load_scene(name).replace(geometry={"roi": roi})
            images = max(n // 20, 200) if name == "paper-fig2" else n  # photon by photon: slower
            seconds = best_time(lambda s=scene, m=images: simulate(s, m, seed=1), repeat)
            tracemalloc.start()
            simulate(scene, images, seed=1)
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            rows.append(
                {
                    "scene": name,
                    "roi": roi,
                    "images": images,
                    "images/s": images / seconds,
                    "peak MB": peak / 1e6,
                    "output MB": images * roi * roi * 8 / 1e6,
                }
            )
    df = pd.DataFrame(rows)
    ideal = df[df["scene"] == "ideal"].set_index("roi")["images/s"]
    df["throughput / ideal"] = df["images/s"] / df["roi"].map(ideal)
    return df


def markdown(df: pd.DataFrame, command: str) -> str:
    from _report import machine

    table = df.copy()
    table["images/s"] = table["images/s"].map(lambda v: f"{v:.3g}")
    for col in ("peak MB", "output MB"):
        table[col] = table[col].map(lambda v: f"{v:.0f}")
    table["throughput / ideal"] = table["throughput / ideal"].map(lambda v: f"{v:.2f}")
    return f"Command: `{command}` on {machine()}.\n\n" + table.to_markdown(index=False)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small run, print only")
    args = parser.parse_args()
    start = time.perf_counter()
    df = run(args.quick)
    command = "python benchmarks/simulate.py" + (" --quick" if args.quick else "")
    text = markdown(df, command)
    print(text)
    print(f"({time.perf_counter() - start:.0f} s)")
    if not args.quick:
        from _report import write_section

        write_section("simulate", text)
    return df


if __name__ == "__main__":
    main()
