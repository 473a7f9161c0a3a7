"""``python -m pipeline.cli``: the ``holefill`` command."""

from . import console_main

if __name__ == "__main__":
    console_main()
