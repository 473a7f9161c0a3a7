"""The stages of a run, one module each, all of the same shape.

Every stage has four slots:

1. a **recipe builder** (pure): the plan and the configuration in, a list of
   small frozen task records out (paths, windows, parameters; never open files
   or configuration objects);
2. a **worker function** at module level (so it pickles by reference), pure
   apart from reading its inputs and writing its own files under names no
   other task uses; it may run twice without harm and returns a small result;
3. a **gather step** on the client that turns the workers' results into the
   stage's result (sorted into plan order, whatever order tasks finished in);
4. a **writer** for the products the stage contributes (``pipeline.outputs``).

Stages, in the order they run (a module imports only stages before it):

- :mod:`.bin_tiles`     one task per input tile: decode once, bin into statistics
- :mod:`.merge_cells`   one task per cell: merge the tiles touching it
- :mod:`.detect_holes`  one task per cell: hole parts, vertical holes, walls
- :mod:`.link_holes`    on the client: holes linked across cells, causes
- :mod:`.write_rasters` one task per cell: the DSM tiles (and later the fill products)

Only :mod:`pipeline.run` (and :mod:`pipeline.cluster`, the client's lifecycle) knows about Dask: it submits each stage's tasks with
their dependencies and gathers the results.
"""
