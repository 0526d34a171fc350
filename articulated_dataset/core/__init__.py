"""The ground floor: errors, units, rotations, the camera, safe writes, worker pools, MuJoCo's
version contract, the sampling-table type, the depth-sensor noise models and the image files.  It imports the standard library, numpy and (in
:mod:`.mujoco_support` and :mod:`.pool`) MuJoCo, and nothing else of the package.
"""
