"""Options shared by several commands, and how options become configuration.

- ``--config FILE``, ``--set SECTION.KEY=VALUE``: every command that reads a configuration;
- ``--out DIR`` (required): ``run``, ``demo``, ``plan``;
- ``--workers N``: ``run``, ``demo``, ``evaluate``;
- ``--scheduler ADDRESS``: ``run``, ``demo``, ``evaluate`` (each says its default);
- ``--progress/--no-progress``: ``run``, ``demo``.

The options that set a configuration key (:data:`OPTION_KEYS`) are applied by
:func:`with_options`, validated like a key of a file.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import click

if TYPE_CHECKING:
    from ..config import Config

config_option = click.option(
    "--config", "config_path", type=click.Path(dir_okay=False), help="TOML configuration file."
)
set_option = click.option(
    "--set",
    "overrides",
    multiple=True,
    metavar="SECTION.KEY=VALUE",
    help="Override one configuration key (repeatable), e.g. --set grid.resolution_m=0.5.",
)
out_option = click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output folder.")
workers_option = click.option("--workers", type=int, help="Local worker processes (dask.workers).")
progress_option = click.option(
    "--progress/--no-progress", default=None, help="Progress bar (default: when stderr is a terminal)."
)


def scheduler_option(text: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """``--scheduler ADDRESS``, with the command's own word on the default."""
    return click.option("--scheduler", help=text)


def progress_shown(progress: bool | None) -> bool:
    """``--progress/--no-progress``, else a bar when stderr is a terminal."""
    import sys

    return sys.stderr.isatty() if progress is None else progress


#: Command-line options that set a configuration key: option -> (section, key).
OPTION_KEYS = {
    "workers": ("dask", "workers"),
    "crs": ("survey", "crs"),
    "target_crs": ("survey", "target_crs"),
    "on_error": ("survey", "on_error"),
    "reader": ("read", "reader"),
    "pdal_pipeline": ("read", "pdal_pipeline"),
}


def with_options(config: Config, **options: Any) -> Config:
    """The configuration with the options given on the command line (validated like a file)."""
    for name, value in options.items():
        if value is not None:
            section, key = OPTION_KEYS[name]
            config = config.replace(section, source=f"--{name.replace('_', '-')} {value}", **{key: value})
    return config
