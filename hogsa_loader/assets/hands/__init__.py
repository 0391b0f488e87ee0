"""Hand models: chumpy-free MANO I/O, the batched MANO layer, MANO-HD and the synthetic hand."""

from hogsa_loader.assets.hands.anatomy import NAMED_POSES, derive_contact_prior, derive_joint_axes, named_articulation
from hogsa_loader.assets.hands.mano import MANOLayer, ManoOutput
from hogsa_loader.assets.hands.mano_io import (
    ManoModelData,
    RestrictedUnpickler,
    convert_mano_to_npz,
    load_mano,
    reorder_vertices,
)
from hogsa_loader.assets.hands.manohd import subdivide_model

__all__ = [
    "MANOLayer",
    "ManoModelData",
    "ManoOutput",
    "NAMED_POSES",
    "RestrictedUnpickler",
    "convert_mano_to_npz",
    "derive_contact_prior",
    "derive_joint_axes",
    "load_mano",
    "named_articulation",
    "reorder_vertices",
    "subdivide_model",
]
