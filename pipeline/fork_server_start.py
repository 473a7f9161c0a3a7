"""The first module the fork server of the local workers imports: a process of holefill's own, its garbage collector paused.

:func:`pipeline.cluster.start_fork_server` lists it before distributed and the stages;
:mod:`pipeline.worker_start`, the last, freezes what they made and lets the collector run
again, so every worker forks with it running over its own objects alone
(:mod:`pipeline.gc_pause`).
"""

from pipeline.gc_pause import own_process, pause

own_process()
pause()
