"""The generated test world: ARCTIC- and H2O-format roots written from procedural assets.

Subjects, cameras, grasping motion and rendered crops (:func:`hogsa_world.writer.generate_world`,
CLI ``hogsa world``), procedural objects (:mod:`hogsa_world.objects`), a synthetic MANO-schema
hand (:mod:`hogsa_world.hand`), the H2O writer, and the demo (:mod:`hogsa_world.demo`, ``hogsa
demo``) that builds a bundle from a world. The library (:mod:`hogsa_loader`) never imports this
package; it needs the ``demo`` extra (scikit-image).
"""

from hogsa_world.presets import PRESETS, SequencePlan, SubjectPlan, WorldPreset, get_preset
from hogsa_world.writer import generate_world

__all__ = ["PRESETS", "SequencePlan", "SubjectPlan", "WorldPreset", "generate_world", "get_preset"]
