"""Per-molecule analysis of a movie (issue 14): posteriors of selected molecules and the files
and tables that come out of them.

``localizations`` turns posterior summary rows into picasso's columns and bayespsf's;
``write_all`` writes them as picasso's ``locs.hdf5`` + ``locs.yaml``, a ThunderSTORM
``locs.csv`` and ``locs.parquet``. ``frame_consistency`` checks, without ground truth, that an
immobile molecule's per-frame posteriors agree within their stated widths;
``width_spread`` gives the paper's experimental Delta s per molecule beside its predictions.
"""

from bayespsf.analysis.consistency import frame_consistency
from bayespsf.analysis.locs import localizations, thunderstorm_table, write_all, write_picasso
from bayespsf.analysis.width_spread import width_spread

__all__ = [
    "frame_consistency",
    "localizations",
    "thunderstorm_table",
    "width_spread",
    "write_all",
    "write_picasso",
]
