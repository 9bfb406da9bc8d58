"""The training loop and what runs it: `loop.train` (Adam over a kind's parameters, its population
control, regularisers and per-step rules, which are core/train's), checkpoints, the log, and the
data-parallel ranks (dataparallel, distributed, launch)."""
