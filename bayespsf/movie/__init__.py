"""From a movie to molecules. Each stage is a plain function usable alone, with an array or a
table in and out:

``read_movie`` opens a movie frame by frame; ``project`` reduces its frames to one image with
bounded memory; ``detect`` / ``detect_movie`` / ``detect_frames`` find candidate molecules with
a stated false-positive rate; ``cut_rois`` cuts each molecule's ROIs over time;
``molecules_over_time`` gives per-frame photons, background and centroid, the bleaching steps
(``bleach_steps``) and the drift; ``select`` applies the paper's selection rules (``Rules``);
``find_molecules`` composes them all; ``estimate_psf_sd`` measures the spot's SD where it is
not stated, and ``geometry_for_psf`` sizes the ROI and its fitted centre from it. The
camera's calibration from a movie is in ``bayespsf.calibration``.
"""

from bayespsf.movie.detect import detect, detect_movie
from bayespsf.movie.extract import RoiStack, cut_rois, iter_rois
from bayespsf.movie.found import FoundMolecules
from bayespsf.movie.frame_detect import (
    detect_frame,
    detect_frames,
    frame_settings,
    iter_detect_frames,
)
from bayespsf.movie.geometry import geometry_for_psf
from bayespsf.movie.pipeline import find_molecules
from bayespsf.movie.project import project
from bayespsf.movie.psf_width import PsfWidth, estimate_psf_sd
from bayespsf.movie.read import Movie, read_movie
from bayespsf.movie.select import Rules, select
from bayespsf.movie.steps import bleach_steps
from bayespsf.movie.traces import molecules_over_time, traces

__all__ = [
    "FoundMolecules",
    "Movie",
    "PsfWidth",
    "RoiStack",
    "Rules",
    "bleach_steps",
    "cut_rois",
    "detect",
    "detect_frame",
    "detect_frames",
    "detect_movie",
    "estimate_psf_sd",
    "find_molecules",
    "frame_settings",
    "geometry_for_psf",
    "iter_detect_frames",
    "iter_rois",
    "molecules_over_time",
    "project",
    "read_movie",
    "select",
    "traces",
]
