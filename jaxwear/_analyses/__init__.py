"""_analyses layer."""
