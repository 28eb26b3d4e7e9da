"""Camera laws: the distribution of a pixel's counts (ADU) given its expected photons."""

from bayespsf.cameras.base import Camera
from bayespsf.cameras.emccd import EMCCD
from bayespsf.cameras.photon import Photon
from bayespsf.cameras.scmos import SCMOS

__all__ = ["EMCCD", "SCMOS", "Camera", "Photon"]
