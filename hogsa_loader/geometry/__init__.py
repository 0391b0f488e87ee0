"""Small, dependency-free geometry helpers (rotations, transforms)."""

from hogsa_loader.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rotation_about_axis

__all__ = ["axis_angle_to_matrix", "matrix_to_axis_angle", "rotation_about_axis"]
