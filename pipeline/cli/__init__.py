"""The ``holefill`` command line: one module per command (as rasterio's ``rio``), thin over library functions.

- :mod:`.group`: the group (``-v``/``-q``, ``--log-format``), exit codes per error class (:data:`EXIT_CODES`);
- :mod:`.options`: the options several commands share, and options -> configuration;
- :mod:`.messages`: messages on stderr (text or JSON lines), logging, a run's summary lines;
- the commands: :mod:`.run`, :mod:`.demo`, :mod:`.evaluate`, :mod:`.plan`, :mod:`.config`.

A new command is a module with a ``click.command`` and one line below.
"""

from __future__ import annotations

from .config import config_command
from .demo import demo_command
from .evaluate import evaluate_command
from .group import EXIT_CODES, EXIT_INTERRUPTED, EXIT_PARTIAL, console_main, main
from .plan import plan_command
from .run import run_command

for _command in (run_command, demo_command, evaluate_command, plan_command, config_command):
    main.add_command(_command)

__all__ = ["EXIT_CODES", "EXIT_INTERRUPTED", "EXIT_PARTIAL", "console_main", "main"]
