"""What every local worker needs ready before its first task, done once in the fork server.

Imported by the server the local workers fork from (:func:`pipeline.cluster.start_fork_server`),
never by the client: a forked worker inherits what the server set up. Each stage's numba
kernels are loaded from numba's cache on their first call, and the first load of a process
sets up numba's code generator (0.2-0.3 s, measured on the 2-core VM); set up here, before
the fork, a worker's first kernel loads in about 15 ms.
"""

from numba.core.registry import cpu_target

# the stages the first tasks run (also distributed's preloads of each worker: imported once, here)
import pipeline.stages.bin_tiles
import pipeline.stages.merge_cells  # noqa: F401
from pipeline.gc_pause import freeze_imports

cpu_target.target_context.refresh()

# the last preload: what the imports made is frozen and the collector runs again (paused by
# pipeline.fork_server_start, the first), so the workers fork with it running over their own objects
freeze_imports()
