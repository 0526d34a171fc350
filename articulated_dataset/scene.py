"""Old home of :mod:`articulated_dataset.generation.scene`, kept only for
``tests/test_manipulation.py`` (``from articulated_dataset.scene import set_configuration``),
which another session is editing; remove this module once that import names
``articulated_dataset.generation.scene``."""

from .generation.scene import set_configuration  # noqa: F401
