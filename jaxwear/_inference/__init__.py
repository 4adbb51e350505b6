"""_inference layer."""
