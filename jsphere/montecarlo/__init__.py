"""Monte-Carlo studies: sampled robots and actuators, batched runs, resumable stores.

`run.monte_carlo` runs a study with its `options.StudyOptions` (`study`: its checks and the study
file of `jsphere montecarlo`; `sampling`, `batch`, `store`, `result`: its draws, batches, folder and
outcome); `distributed` shares its batches over a JAX multi-process job, `workers` (with `claims`)
over independent jobs that share its folder.
"""

from .options import Distributed as Distributed
from .options import StudyOptions as StudyOptions
from .store import read_result as read_result
