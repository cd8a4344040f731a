"""Synthetic world in the exact nuScenes on-disk format: road network, map expansion, tables, renderer.

``generate_world(out, ...)`` writes a dataroot that ``nuscenes.NuScenes`` and ``NuScenesMap`` load
unmodified (see world.py); ``preview.write_preview`` draws one sample with its map for a visual check.
"""

from .world import VERSION, generate_world, read_manifest

__all__ = ["VERSION", "generate_world", "read_manifest"]
