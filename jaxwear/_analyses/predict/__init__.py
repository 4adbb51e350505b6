"""_analyses/predict layer."""
