"""Datasets: the Scene base class, the formats (built-in, Blender, LLFF, COLMAP), rays and the datamodule."""
