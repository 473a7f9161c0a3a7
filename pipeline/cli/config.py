"""``holefill config``: validate a configuration, and print it resolved."""

from __future__ import annotations

import click

from .messages import note
from .options import config_option, set_option


@click.command("config")
@click.option("--show", is_flag=True, help="Print the resolved configuration as TOML.")
@config_option
@set_option
def config_command(show: bool, config_path: str | None, overrides: tuple[str, ...]) -> None:
    """Validate a configuration (and print it with --show)."""
    from ..config import load_config

    config = load_config(config_path, list(overrides))
    if show:
        click.echo(config.to_toml())
    else:
        note("configuration is valid")
