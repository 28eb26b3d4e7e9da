"""From a movie to molecules: reading movies and projecting them over time (issue 13).

Each stage is a plain function usable alone: ``read_movie`` opens a movie for reading frame by
frame, ``project`` reduces its frames to one image with memory bounded independently of the
number of frames.
"""

from bayespsf.movie.project import project
from bayespsf.movie.read import Movie, read_movie

__all__ = ["Movie", "project", "read_movie"]
