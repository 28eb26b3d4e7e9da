"""Axial position from the spot's widths (issue 16): defocus curves and the bounds on z."""
