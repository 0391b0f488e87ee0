"""Synthetic ARCTIC-format worlds: subjects, cameras, grasping motion, rendered crops.

Entry point: :func:`hogsa_loader.synthetic.world.writer.generate_world` (CLI: ``hogsa world``).
"""

from hogsa_loader.synthetic.world.presets import PRESETS, SequencePlan, SubjectPlan, WorldPreset, get_preset
from hogsa_loader.synthetic.world.writer import generate_world

__all__ = ["PRESETS", "SequencePlan", "SubjectPlan", "WorldPreset", "generate_world", "get_preset"]
