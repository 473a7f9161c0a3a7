"""The sensor's geometry: flight lines, the sensor's trajectory, swaths and lines of sight.

Modules in data-flow order: ``sums`` (stage 1: mergeable sums per flight line and time
bin), ``trajectory`` (the client: each line's trajectory and swath), ``sight`` (per
cell: which swaths cover a pixel, and whether the sensor saw it unobstructed).
Pure: arrays in, arrays out; no I/O, no Dask, no configuration objects.
"""
