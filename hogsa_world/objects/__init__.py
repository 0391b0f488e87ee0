"""Procedural textured articulated objects under ARCTIC's object names."""
