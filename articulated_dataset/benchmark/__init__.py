"""The benchmark: what a method hands in, and how it is scored against the truth shards.

* :mod:`.predictions` -- the ``predictions.h5`` format (:func:`write_predictions`,
  :func:`read_predictions`, validation);
* :mod:`.metrics` -- every per-image metric as a vectorised formula (docs/scoring.md);
* :mod:`.truth` -- the labels of one truth split and the choice of one split per class;
* :mod:`.scoring` -- :func:`score`: predictions against the truth, per image, then aggregated;
* :mod:`.report` -- the metric table, :class:`ScoreRow` and the printed/JSON/CSV :class:`Report`;
* :mod:`.pointlik` -- the paper's Table 2 procedure: axis origins snapped to the most likely
  point of the object's cloud under a predicted mixture.

Importing this package imports neither MuJoCo, OpenGL, torch nor jax.
"""

from articulated_dataset.benchmark.predictions import read_predictions, write_predictions
from articulated_dataset.benchmark.report import Report, ScoreRow
from articulated_dataset.benchmark.scoring import score

__all__ = ["Report", "ScoreRow", "read_predictions", "score", "write_predictions"]
