"""The console commands, one module per script (``pyproject.toml``'s ``[project.scripts]``): each parses its
command line and calls the library; nothing imports a command. ``arguments``, ``console`` and ``signals``
are what the commands share: their command lines, their console, and the signals that end them."""
