"""Dense, translation-equivariant estimator of articulation (``artdata train --model dense``).

A small fully convolutional network reads the depth image back-projected to camera-frame
points with the image's intrinsics (so any camera works) and predicts, for every output
pixel: the part it sees (background / body / part j), each joint's axis origin as an
offset from the pixel's own 3-D point, the axis frame's rotation (6-D), the configuration
q, the part offset and the object's geometry, with confidences.  The image estimate comes
from the pixels' votes: mean-shift finds the modes of the origin votes, so a two-sided
ambiguity (a closed cabinet's hinge) yields two weighted mixture components, never their
average (:mod:`articulated_dataset.methods.dense.aggregate`).

Modules: :mod:`.features` (depth + K -> network input, labels -> pixel targets),
:mod:`.model` (the network), :mod:`.aggregate` (votes -> point estimate and mixture),
:mod:`.data` (a split in memory at the model resolution), :mod:`.checkpoint` (a checkpoint
read, checked and its network rebuilt), :mod:`.train` (training with checkpoints and
resume), :mod:`.predict` (splits and single images), :mod:`.refine` (the geometric refinement
of the voted estimate) and :mod:`.fit` (which refinement steps a model uses, chosen on its
validation objects).
"""
