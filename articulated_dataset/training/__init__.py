"""What a learning method reads: the loaders over the shards (:mod:`.loaders`), the training
targets built from the labels (:mod:`.targets`) and the per-sample transforms
(:mod:`.transforms`).  Importing this package imports neither torch nor jax.
"""
