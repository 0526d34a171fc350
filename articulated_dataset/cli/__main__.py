"""``python -m articulated_dataset.cli``: the ``artdata`` command."""

from . import main

main()
