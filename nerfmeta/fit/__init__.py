"""The one fit loop, its ray sampler, checkpoints, evaluation and run folders."""
