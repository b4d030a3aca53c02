"""jsphere: a differentiable JAX simulator of a spherical robot driven by an internal omniwheel
platform, after Karavaev & Kilin, "Nonholonomic dynamics and control of a spherical robot with
an internal omniwheel platform: theory and experiments", Proc. Steklov Inst. Math. 295 (2016).

Equation numbers in docstrings refer to that paper; `docs/model.md` lists every convention
and every correction of the paper's typos.

float64 is switched on at import (the paper's numbers are at the 0.1 mm level). Set the
environment variable `JSPHERE_X64=0` before importing to keep JAX's float32 default.
"""

import os as _os

import jax as _jax

if _os.environ.get("JSPHERE_X64", "1") != "0":
    _jax.config.update("jax_enable_x64", True)

from .capture.c3d import read_c3d as read_c3d
from .capture.convert import convert_raw as convert_raw
from .capture.body import read_body_markers as read_body_markers
from .capture.inputs import read_inputs_csv as read_inputs_csv, write_inputs_csv as write_inputs_csv
from .capture.markers import MarkerData as MarkerData
from .capture.motive import read_motive_csv as read_motive_csv, write_motive_csv as write_motive_csv
from .capture.pose import markers_to_trial as markers_to_trial, rigid_body_pose as rigid_body_pose
from .capture.synthetic import (
    random_inputs as random_inputs,
    synthetic_markers as synthetic_markers,
    synthetic_trial as synthetic_trial,
)
from .capture.trial import Trial as Trial, read_trial as read_trial, read_trials as read_trials, write_trial as write_trial
from .capture.validation import CaptureWarning as CaptureWarning
from .capture.vicon import read_vicon_csv as read_vicon_csv, write_vicon_csv as write_vicon_csv

from ._runtime.errors import ExitCode as ExitCode, InputError as InputError, SolverFailure as SolverFailure
from .identify.fit import fit as fit
from .identify.least_squares import LeastSquaresResult as LeastSquaresResult, least_squares as least_squares
from .identify.report import FitResult as FitResult
from .identify.free import FreeParams as FreeParams

from .controls import (
    Constant as Constant,
    Sampled as Sampled,
    StraightLine as StraightLine,
    Torques as Torques,
    WheelSpeeds as WheelSpeeds,
    Zero as Zero,
    kinematic_control as kinematic_control,
    straight_line as straight_line,
)
from .model.dynamics import (
    accelerations as accelerations,
    dissipation as dissipation,
    energy as energy,
    kinetic_energy as kinetic_energy,
    potential_energy as potential_energy,
    power as power,
)
from .gaits.gaits import (
    Gait as Gait,
    SinSquared as SinSquared,
    acceleration as acceleration,
    braking as braking,
    simulate_gaits as simulate_gaits,
    turn as turn,
)
from .model.kinematics import (
    constraint_residuals as constraint_residuals,
    kinematic_wheel_speeds as kinematic_wheel_speeds,
    relative_rate_from_wheel_speeds as relative_rate_from_wheel_speeds,
    rolling_velocity as rolling_velocity,
    wheel_speeds as wheel_speeds,
)
from .montecarlo.result import MonteCarloResult as MonteCarloResult
from .montecarlo.run import monte_carlo as monte_carlo
from .montecarlo.sampling import Actuators as Actuators
from .montecarlo.store import MonteCarloWarning as MonteCarloWarning
from .model.names import get_value as get_value, parse_name as parse_name, set_value as set_value
from .model.params import RobotParams as RobotParams
from .paper.reproduce import reproduce as reproduce, to_figure_frame as to_figure_frame
from .solve.simulate import simulate as simulate
from .solve.options import SolverOptions as SolverOptions
from .solve.status import RESULTS as RESULTS
from .model.state import State as State
from .solve.trajectory import (
    Trajectory as Trajectory,
    energy_along as energy_along,
    power_along as power_along,
    trajectory_residuals as trajectory_residuals,
)
from .gaits.families import (
    Smooth as Smooth,
    TiltGait as TiltGait,
    paper_gait as paper_gait,
    smooth_gait as smooth_gait,
    tilt_to_gamma as tilt_to_gamma,
)
from .planning.optimise import optimise_gaits as optimise_gaits
from .planning.plan import (
    Limits as Limits,
    Objective as Objective,
    Plan as Plan,
    PlanInfeasibleError as PlanInfeasibleError,
    PlanSettings as PlanSettings,
    plan as plan,
    plan_many as plan_many,
    plan_route as plan_route,
)
from .planning.verify import replay_errors as replay_errors

__version__ = "0.1.0"
