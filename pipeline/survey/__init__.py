"""The survey's facts, before any point is binned, and the ones stage 1 settles.

- :mod:`.scan`: input discovery, the header scan, CRS and unit decisions (``Survey``,
  ``Tile``, ``scan_survey``);
- :mod:`.density`: pure rules from counts and areas (the auto pixel size, cell rounding,
  the sampling-gap width, auto ``min_area_m2``);
- :mod:`.footprint_density`: the density pre-pass on the data footprint, and the local
  sampling-gap width per hole;
- :mod:`.footprint`: the AOI at pixel level (survey area x data footprint; pure);
- :mod:`.tile_grid`: whether the tiles lie on a grid of squares, and its survey area (pure);
- :mod:`.ground_level`: whether the heights are above the ground (pure).

Nothing is imported here, so that a kernel importing :mod:`.density` or :mod:`.footprint`
loads no I/O library: import from the modules.
"""
