"""jsphere: a differentiable JAX simulator of a spherical robot driven by an internal omniwheel
platform, after Karavaev & Kilin, "Nonholonomic dynamics and control of a spherical robot with
an internal omniwheel platform: theory and experiments", Proc. Steklov Inst. Math. 295 (2016).

Equation numbers in docstrings refer to that paper; `docs/model.md` lists every convention
and every correction of the paper's typos.

Importing jsphere changes no global state. Its numbers (the paper's are at the 0.1 mm level)
need float64, which JAX leaves off: switch it on before creating arrays, with
`jax.config.update("jax_enable_x64", True)` or `jsphere.enable_x64()`. A solve that runs in
float32 only because float64 is off warns once (`PrecisionWarning`).
"""

from ._runtime.compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._runtime.errors import ExitCode as ExitCode
from ._runtime.errors import InputError as InputError
from ._runtime.errors import SolverFailure as SolverFailure
from ._runtime.precision import PrecisionWarning as PrecisionWarning
from ._runtime.precision import enable_x64 as enable_x64
from .capture.body import read_body_markers as read_body_markers
from .capture.c3d import read_c3d as read_c3d
from .capture.convert import convert_raw as convert_raw
from .capture.inputs import read_inputs_csv as read_inputs_csv
from .capture.inputs import write_inputs_csv as write_inputs_csv
from .capture.markers import MarkerData as MarkerData
from .capture.motive import read_motive_csv as read_motive_csv
from .capture.motive import write_motive_csv as write_motive_csv
from .capture.pose import markers_to_trial as markers_to_trial
from .capture.pose import rigid_body_pose as rigid_body_pose
from .capture.synthetic import (
    random_inputs as random_inputs,
)
from .capture.synthetic import (
    synthetic_markers as synthetic_markers,
)
from .capture.synthetic import (
    synthetic_trial as synthetic_trial,
)
from .capture.trial import (
    Trial as Trial,
)
from .capture.trial import (
    read_trial as read_trial,
)
from .capture.trial import (
    read_trials as read_trials,
)
from .capture.trial import (
    write_trial as write_trial,
)
from .capture.validation import CaptureWarning as CaptureWarning
from .capture.vicon import read_vicon_csv as read_vicon_csv
from .capture.vicon import write_vicon_csv as write_vicon_csv
from .controls import (
    Constant as Constant,
)
from .controls import (
    Sampled as Sampled,
)
from .controls import (
    StraightLine as StraightLine,
)
from .controls import (
    Torques as Torques,
)
from .controls import (
    WheelSpeeds as WheelSpeeds,
)
from .controls import (
    Zero as Zero,
)
from .controls import (
    kinematic_control as kinematic_control,
)
from .controls import (
    straight_line as straight_line,
)
from .gaits.families import (
    Smooth as Smooth,
)
from .gaits.families import (
    TiltGait as TiltGait,
)
from .gaits.families import (
    paper_gait as paper_gait,
)
from .gaits.families import (
    smooth_gait as smooth_gait,
)
from .gaits.families import (
    tilt_to_gamma as tilt_to_gamma,
)
from .gaits.gaits import (
    Gait as Gait,
)
from .gaits.gaits import (
    SinSquared as SinSquared,
)
from .gaits.gaits import (
    acceleration as acceleration,
)
from .gaits.gaits import (
    braking as braking,
)
from .gaits.gaits import (
    simulate_gaits as simulate_gaits,
)
from .gaits.gaits import (
    turn as turn,
)
from .identify.fit import fit as fit
from .identify.free import FreeParams as FreeParams
from .identify.least_squares import LeastSquaresResult as LeastSquaresResult
from .identify.least_squares import least_squares as least_squares
from .identify.report import FitResult as FitResult
from .model.dynamics import (
    accelerations as accelerations,
)
from .model.dynamics import (
    dissipation as dissipation,
)
from .model.dynamics import (
    energy as energy,
)
from .model.dynamics import (
    kinetic_energy as kinetic_energy,
)
from .model.dynamics import (
    potential_energy as potential_energy,
)
from .model.dynamics import (
    power as power,
)
from .model.kinematics import (
    constraint_residuals as constraint_residuals,
)
from .model.kinematics import (
    kinematic_wheel_speeds as kinematic_wheel_speeds,
)
from .model.kinematics import (
    relative_rate_from_wheel_speeds as relative_rate_from_wheel_speeds,
)
from .model.kinematics import (
    rolling_velocity as rolling_velocity,
)
from .model.kinematics import (
    wheel_speeds as wheel_speeds,
)
from .model.names import get_value as get_value
from .model.names import parse_name as parse_name
from .model.names import set_value as set_value
from .model.params import RobotParams as RobotParams
from .model.state import State as State
from .montecarlo.result import MonteCarloResult as MonteCarloResult
from .montecarlo.run import monte_carlo as monte_carlo
from .montecarlo.sampling import Actuators as Actuators
from .montecarlo.store import MonteCarloWarning as MonteCarloWarning
from .paper.reproduce import reproduce as reproduce
from .paper.reproduce import to_figure_frame as to_figure_frame
from .planning.optimise import optimise_gaits as optimise_gaits
from .planning.plan import (
    Limits as Limits,
)
from .planning.plan import (
    Objective as Objective,
)
from .planning.plan import (
    Plan as Plan,
)
from .planning.plan import (
    PlanInfeasibleError as PlanInfeasibleError,
)
from .planning.plan import (
    PlanSettings as PlanSettings,
)
from .planning.plan import (
    plan as plan,
)
from .planning.plan import (
    plan_many as plan_many,
)
from .planning.plan import (
    plan_route as plan_route,
)
from .planning.verify import replay_errors as replay_errors
from .solve.options import SolverOptions as SolverOptions
from .solve.simulate import simulate as simulate
from .solve.status import RESULTS as RESULTS
from .solve.trajectory import (
    Trajectory as Trajectory,
)
from .solve.trajectory import (
    energy_along as energy_along,
)
from .solve.trajectory import (
    power_along as power_along,
)
from .solve.trajectory import (
    trajectory_residuals as trajectory_residuals,
)

__version__ = "0.1.0"
