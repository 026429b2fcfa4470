"""Pictures without GL: a software rasteriser for meshes and markers."""
