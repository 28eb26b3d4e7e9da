"""Every file format, one module per format: ROI stacks (``rois``), the camera file
(``camera_file``), z calibrations (``z_calibration``), localisation tables (``locs``:
picasso's ``locs.hdf5`` + ``locs.yaml``, ThunderSTORM's CSV, Parquet), an output folder's
run record (``run_record``: ``run.json``, which keeps one run's results per folder) and the
check of an output folder before a run writes into it (``folders``)."""

from bayespsf.io.camera_file import (
    CAMERA_KEYS,
    camera_file_text,
    camera_scene,
    read_camera_file,
    write_camera_file,
)
from bayespsf.io.locs import thunderstorm_table, write_locs, write_picasso
from bayespsf.io.rois import read_rois
from bayespsf.io.run_record import RunConflict, check_folder, claim_folder, read_run_record
from bayespsf.io.z_calibration import read_z_calibration, write_z_calibration

__all__ = [
    "CAMERA_KEYS",
    "RunConflict",
    "camera_file_text",
    "camera_scene",
    "check_folder",
    "claim_folder",
    "read_camera_file",
    "read_rois",
    "read_run_record",
    "read_z_calibration",
    "thunderstorm_table",
    "write_camera_file",
    "write_locs",
    "write_picasso",
    "write_z_calibration",
]
