"""Command line interface ``hybrid-pk``."""
