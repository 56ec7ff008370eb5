"""Background colours by name: what a ray shows where it absorbs nothing (``data.background``)."""

BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
