"""Perception: recordings on disk, cameras, RGB-D fusion into world point sets, synthetic recordings.

- :mod:`.recording`: :class:`Recording` (read, validated, lazy, never writes), :class:`RecordingWriter`,
  :func:`write_recording`, :class:`RecordingError`, :func:`controls_to_end_effectors`.
- :mod:`.cameras`: pinhole :class:`Camera` (OpenCV axes), projection and depth back-projection.
- :mod:`.fusion`: multi-view fusion, table plane by RANSAC, frame-0 particles, controls from hand masks.
- :mod:`.synth`: ``empm synth``, synthetic recordings with known material parameters.
"""

from .cameras import Camera, backproject_depth, intrinsics_matrix, look_at, project_points
from .fusion import (close_against_table, controls_from_masks, estimate_table_plane, fit_table_plane, frame_points,
                     fuse_frame, fuse_views, initial_particles, load_controls, remove_statistical_outliers,
                     smooth_points, voxel_downsample)
from .recording import (Recording, RecordingError, RecordingWriter, controls_to_end_effectors,
                        end_effector_velocities, load_calibration_pickle, validate_controls, write_recording)

__all__ = [
    "Camera", "backproject_depth", "intrinsics_matrix", "look_at", "project_points",
    "close_against_table", "controls_from_masks", "estimate_table_plane", "fit_table_plane", "frame_points",
    "fuse_frame", "fuse_views", "initial_particles", "load_controls", "remove_statistical_outliers",
    "smooth_points", "voxel_downsample",
    "Recording", "RecordingError", "RecordingWriter", "controls_to_end_effectors", "end_effector_velocities",
    "load_calibration_pickle", "validate_controls", "write_recording",
]
