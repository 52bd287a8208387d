"""``python -m planetref``: the same as the ``planetref`` command."""

from planetref.cli import main

if __name__ == "__main__":
    main()
