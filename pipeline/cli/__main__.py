"""``python -m pipeline.cli``: the ``holefill`` command."""

from . import main

if __name__ == "__main__":
    main()
