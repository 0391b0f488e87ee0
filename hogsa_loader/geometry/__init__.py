"""Geometry every stage uses: rotations (:mod:`.rotations`, :mod:`.quaternion`), camera
placement (:mod:`.cameras`), mesh normals (:mod:`.meshes`) and texture lookup (:mod:`.texture`)."""

from hogsa_loader.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rotation_about_axis

__all__ = ["axis_angle_to_matrix", "matrix_to_axis_angle", "rotation_about_axis"]
