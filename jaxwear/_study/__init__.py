"""_study layer."""
