"""From a movie to molecules (issue 13). Each stage is a plain function usable alone, with an
array or a table in and out:

``read_movie`` opens a movie frame by frame; ``project`` reduces its frames to one image with
bounded memory; ``detect`` / ``detect_movie`` / ``detect_frames`` find candidate molecules with
a stated false-positive rate; ``cut_rois`` cuts each molecule's ROIs over time;
``molecules_over_time`` gives per-frame photons, background and centroid, the bleaching steps
(``bleach_steps``) and the drift; ``select`` applies the paper's selection rules (``Rules``);
``dark_calibration`` gives a camera's offset and readout noise from its dark frames,
``flat_field_gain`` an sCMOS camera's per-pixel gain from flat fields, and
``gain_from_molecules`` its ADU per photon from the movie's immobile molecules (Eq. photonConv).
"""

from bayespsf.movie.calibrate import (
    DarkCalibration,
    FlatFieldGain,
    dark_calibration,
    flat_field_gain,
)
from bayespsf.movie.detect import detect, detect_frames, detect_movie
from bayespsf.movie.extract import RoiStack, cut_rois, iter_rois
from bayespsf.movie.gain import GainEstimate, gain_from_molecules
from bayespsf.movie.project import project
from bayespsf.movie.read import Movie, read_movie
from bayespsf.movie.select import Rules, select
from bayespsf.movie.steps import bleach_steps
from bayespsf.movie.traces import molecules_over_time, traces

__all__ = [
    "DarkCalibration",
    "FlatFieldGain",
    "GainEstimate",
    "Movie",
    "RoiStack",
    "Rules",
    "bleach_steps",
    "cut_rois",
    "dark_calibration",
    "detect",
    "detect_frames",
    "detect_movie",
    "flat_field_gain",
    "gain_from_molecules",
    "iter_rois",
    "molecules_over_time",
    "project",
    "read_movie",
    "select",
    "traces",
]
