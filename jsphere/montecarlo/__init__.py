"""Monte-Carlo studies: sampled robots and actuators, batched runs, resumable stores.

`run.monte_carlo` runs a study; `study` checks its description (and reads the study file of
`jsphere montecarlo`), `sampling` draws each trial's robot and actuator errors, `batch` is the
compiled function of one batch, `store` the study's folder, `result` the outcome and its
statistics. Beyond one process: `distributed` shards every batch over the devices of a JAX
multi-process job, `workers` lets independent jobs share a study's folder (`claims`) and
gathers their batches.
"""
