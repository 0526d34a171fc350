"""``python -m articulated_dataset.cli``: the ``artdata`` command."""

from articulated_dataset.cli import main

main()
