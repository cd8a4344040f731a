"""InstaGraM: instance-level graph modeling for vectorized HD map learning.

The public Python API (mapper.py): maps from your own cameras.

    from instagram_hdmap import Mapper
    mapper = Mapper.from_checkpoint("runs/demo/run/last.pt")
    elements = mapper(images=images, intrinsics=intrinsics, cam_to_ego=cam_to_ego)
"""

from .mapper import Frame, MapElement, Mapper, MapStream, to_hdmapnet

__version__ = "0.1.0"
__all__ = ["Frame", "MapElement", "MapStream", "Mapper", "__version__", "to_hdmapnet"]
