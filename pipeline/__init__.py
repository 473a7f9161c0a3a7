"""holefill: complete, trustworthy surface models from airborne lidar surveys.

The package is laid out by pipeline stage (see docs/architecture.md):
``config`` -> ``survey`` -> ``grid`` -> ``rasterize`` -> ``holes`` -> ``fill``
-> outputs, with ``run`` (graphs) and ``cluster`` (the client) the only modules that know about Dask.
"""

__version__ = "0.1.0"
