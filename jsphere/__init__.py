import jax
jax.config.update("jax_enable_x64", True)
from ._params import RobotParams
from ._dynamics import accelerations, energy, power
from ._kinematics import wheel_speeds
from ._state import State
from ._controls import Torques, WheelSpeeds, kinematic_control, straight_line
from ._simulate import simulate, Trajectory
from ._gaits import Gait, SinSquared, Constant, acceleration, braking, turn, simulate_gaits
