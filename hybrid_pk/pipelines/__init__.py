"""Pipelines: whole jobs built from the layers below (the demo)."""
