"""Pipelines: whole jobs built from the layers below (the demo)."""

from hybrid_pk.pipelines.demo import DemoResult, run_demo

__all__ = ["DemoResult", "run_demo"]
