"""Scene to images: the simulator applies exactly the effects a scene declares (``effects``,
one class per effect), for single ROIs (``simulate``, ``simulate_chunks``), movies of many
molecules (``simulate_movie``) and bead z-stacks (``simulate_zstack``)."""

from bayespsf.simulation.movie import iter_movie, match_truth, simulate_movie
from bayespsf.simulation.pipeline import build_pipeline, describe, simulate, simulate_chunks
from bayespsf.simulation.zstack import simulate_zstack, zstack_positions

__all__ = [
    "build_pipeline",
    "describe",
    "iter_movie",
    "match_truth",
    "simulate",
    "simulate_chunks",
    "simulate_movie",
    "simulate_zstack",
    "zstack_positions",
]
