"""Objects: ARCTIC articulated templates and layer, H2O rigid poses, procedural objects.

ARCTIC's conventions hold throughout: templates in metres in a canonical frame whose z
axis is the hinge; ``parts.json`` 0 = top (articulated), 1 = bottom (base); the top
rotates by ``R_z(-θ)`` before the global pose.
"""

from hogsa_loader.assets.objects.articulated import (
    ARTICULATION_AXIS,
    ArticulatedObjectLayer,
    articulate,
    articulation_matrix,
)
from hogsa_loader.assets.objects.rigid import H2O_OBJECT_NAMES, parse_h2o_obj_pose_rt, pose_rigid, read_h2o_obj_pose_rt
from hogsa_loader.assets.objects.template import (
    BOTTOM,
    OBJECT_NAMES,
    TOP,
    ObjectTemplate,
    load_object_template,
    load_object_templates,
    read_object_meta,
)

__all__ = [
    "ARTICULATION_AXIS",
    "ArticulatedObjectLayer",
    "BOTTOM",
    "H2O_OBJECT_NAMES",
    "OBJECT_NAMES",
    "ObjectTemplate",
    "TOP",
    "articulate",
    "articulation_matrix",
    "load_object_template",
    "load_object_templates",
    "parse_h2o_obj_pose_rt",
    "pose_rigid",
    "read_h2o_obj_pose_rt",
    "read_object_meta",
]
