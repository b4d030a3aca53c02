"""Monte-Carlo studies: sampled robots and actuators, batched runs, resumable stores.

`run.monte_carlo` runs a study with its `options.StudyOptions`; `study` checks its
distributions (and reads the study file of `jsphere montecarlo`, whose keys are the options'
fields), `sampling` draws each trial's robot and actuator errors, `batch` is the compiled
function of one batch, `store` the study's folder (`store.read_result` reads one back),
`result` the outcome and its statistics. Beyond one process: `distributed` shards every batch
over the devices of a JAX multi-process job (one allocation), `workers` lets independent jobs
share a study's folder (`claims`) and gathers their batches (a scheduler's array of jobs).
"""

from .options import Distributed as Distributed
from .options import StudyOptions as StudyOptions
from .store import read_result as read_result
