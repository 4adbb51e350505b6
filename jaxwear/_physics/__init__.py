"""_physics layer."""
