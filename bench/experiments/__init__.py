"""Experiments (floor 3): each decides which runs its table needs and reuses recorded ones.

An experiment is a YAML file in conf/experiment/ whose `experiment.kind` names a module here with a
`run(ctx, **params)` function; the other keys of `experiment` are its params.
"""
# the experiment kinds: modules of this package with a run(ctx, ...) (the others are steps they share)
KINDS = ("table", "one_model", "data", "references", "macs", "stability", "timing", "speed", "lr_range", "claims", "adopt",
         "migrate")
# kinds that read no recorded runs: a run archive elsewhere changes nothing for them
RUNLESS_KINDS = ("macs", "speed")
