"""Tools over generated data: :mod:`.verify` (the checks of ``artdata verify``), :mod:`.viz`
(``artdata show`` and the galleries) and :mod:`.exr` (``artdata export`` / ``import-exr``).
"""
