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

A stage module ends with its :class:`~.stage.Stage` record (recipe builder,
worker, key, label, gather, and how its tasks are scheduled);
:mod:`.registry` lists the records in the order they run (``STAGES``) and
turns what they gathered into one frozen ``RunResults`` for the products.

Stages, in the order they run (a module imports only stages before it):

- :mod:`.bin_tiles`     one task per input tile: decode once, bin into statistics; the file's
                        size, time and SHA-256 for the manifest
- :mod:`.merge_cells`   one task per cell: merge the tiles touching it
- :mod:`.detect_holes`  one task per cell: hole parts, vertical holes, walls
- :mod:`.link_holes`    on the client: holes linked across cells, causes
- :mod:`.fill_holes`    one task per cell owning holes: each hole filled whole
- :mod:`.write_rasters` one task per cell: the DSM tiles and the fill products
- :mod:`.write_points`  one task per tile: the repaired point clouds

Only :mod:`pipeline.run` (and :mod:`pipeline.cluster`, the client's lifecycle) knows about Dask: it walks
the records, submits each stage's tasks with their dependencies and gathers the results.
"""
