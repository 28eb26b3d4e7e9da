"""Per-molecule results from per-frame posteriors: ``analyze`` runs a movie end to end;
``localizations`` gives the localisation table; ``frame_consistency`` checks, without ground
truth, that an immobile molecule's per-frame posteriors agree within their stated widths;
``width_spread`` gives the paper's experimental Delta s per molecule beside its predictions;
``mean_residuals`` and ``width_by_window`` look for model misfit; ``localize_frames`` localises
every spot of every frame in its own frame (blinking or moving molecules)."""

from bayespsf.analysis.consistency import frame_consistency
from bayespsf.analysis.localizations import localizations
from bayespsf.analysis.misfit import mean_residuals, width_by_window
from bayespsf.analysis.per_frame import FrameLocalizations, frame_spots, localize_frames
from bayespsf.analysis.pipeline import Analysis, analyze
from bayespsf.analysis.width_spread import width_spread

__all__ = [
    "Analysis",
    "FrameLocalizations",
    "analyze",
    "frame_consistency",
    "frame_spots",
    "localizations",
    "localize_frames",
    "mean_residuals",
    "width_by_window",
    "width_spread",
]
