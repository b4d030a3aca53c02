"""jsphere: a differentiable JAX simulator of a spherical robot driven by an internal omniwheel
platform, after Karavaev & Kilin, "Nonholonomic dynamics and control of a spherical robot with
an internal omniwheel platform: theory and experiments", Proc. Steklov Inst. Math. 295 (2016).

Equation numbers in docstrings refer to that paper; `docs/model.md` lists every convention
and every correction of the paper's typos.

Importing jsphere changes no global state. Its numbers (the paper's are at the 0.1 mm level)
need float64, which JAX leaves off: switch it on before creating arrays, with
`jax.config.update("jax_enable_x64", True)` or `jsphere.enable_x64()`. A solve that runs in
float32 only because float64 is off warns once (`PrecisionWarning`).

The names below are imported when first used (PEP 562), so that `import jsphere` and the
command line's `--help` do not import JAX; `from jsphere import X` and `jsphere.X` work as
for any module.
"""

import importlib as _importlib

__version__ = "0.1.0"

#: every public name, by the module that defines it
_EXPORTS = {
    "_runtime.compilation_cache": ("enable_compilation_cache",),
    "_runtime.cores": ("shard_trials", "use_cpu_cores"),
    "_runtime.errors": ("ExitCode", "InputError", "SolverFailure"),
    "_runtime.precision": ("PrecisionWarning", "enable_x64"),
    "capture.body": ("read_body_markers",),
    "capture.c3d": ("read_c3d",),
    "capture.clock": ("estimate_time_offset",),
    "capture.convert": ("convert_raw",),
    "capture.inputs": ("read_inputs_csv", "write_inputs_csv"),
    "capture.markers": ("MarkerData",),
    "capture.options": ("ConvertOptions",),
    "capture.motive": ("read_motive_csv", "write_motive_csv"),
    "capture.pose": ("markers_to_trial", "rigid_body_pose"),
    "capture.qualisys": ("read_qualisys_tsv",),
    "capture.rosbag": ("read_rosbag_inputs", "read_rosbag_poses"),
    "capture.onboard": (
        "OnboardNoise",
        "OnboardTrial",
        "read_onboard_trial",
        "synthetic_onboard_trial",
        "write_onboard_trial",
    ),
    "capture.synthetic": ("random_inputs", "synthetic_markers", "synthetic_trial"),
    "capture.trial": ("Trial", "read_trial", "read_trials", "write_trial"),
    "capture.validation": ("CaptureWarning",),
    "capture.vicon": ("read_vicon_csv", "write_vicon_csv"),
    "cli.animate": ("animate",),
    "controls": (
        "Constant",
        "Sampled",
        "StraightLine",
        "Torques",
        "WheelSpeeds",
        "Zero",
        "kinematic_control",
        "straight_line",
    ),
    "design.excitation": ("DesignOptions", "design_excitation"),
    "design.result": ("DesignResult",),
    "gaits.families": ("Smooth", "TiltGait", "paper_gait", "smooth_gait", "tilt_to_gamma"),
    "gaits.gaits": ("Gait", "SinSquared", "acceleration", "braking", "simulate_gaits", "turn"),
    "identify.compare": ("CompareResult", "compare"),
    "identify.options": ("FitOptions",),
    "identify.fit": ("fit",),
    "identify.free": ("FreeParams",),
    "numerics.least_squares": ("LeastSquaresResult", "least_squares"),
    "identify.report": ("FitResult",),
    "model.dynamics": ("accelerations", "dissipation", "energy", "kinetic_energy", "potential_energy", "power"),
    "model.kinematics": (
        "constraint_residuals",
        "kinematic_wheel_speeds",
        "relative_rate_from_wheel_speeds",
        "rolling_velocity",
        "wheel_speeds",
    ),
    "model.limits": ("Limits",),
    "model.names": ("get_value", "parse_name", "set_value"),
    "model.params": ("RobotParams",),
    "model.sensors": ("Mounting", "imu_readings"),
    "model.state": ("State",),
    "model.uncertainty": ("Uncertainty",),
    "montecarlo.options": ("StudyOptions",),
    "montecarlo.result": ("MonteCarloResult",),
    "montecarlo.run": ("monte_carlo",),
    "montecarlo.sampling": ("Actuators",),
    "montecarlo.store": ("MonteCarloWarning",),
    "paper.reproduce": ("reproduce", "to_figure_frame"),
    "planning.optimise": ("optimise_gaits",),
    "planning.plan": (
        "DirectSettings",
        "Objective",
        "Plan",
        "PlanInfeasibleError",
        "PlanOptions",
        "PlanSettings",
        "plan",
        "plan_many",
        "plan_route",
    ),
    "planning.robust": ("RobustOptions", "RobustPlan", "miss_distribution", "plan_robust"),
    "planning.tracking": ("TrackConditions", "TrackWeights", "Tracker", "read_track_csv", "track"),
    "planning.verify": ("replay_errors",),
    "solve.options": ("SolverOptions",),
    "solve.simulate": ("simulate",),
    "solve.status": ("RESULTS",),
    "solve.trajectory": ("Trajectory", "energy_along", "power_along", "trajectory_residuals"),
}

_WHERE = {name: module for module, names in _EXPORTS.items() for name in names}
#: the subpackages, imported on first use as well (`jsphere.model.params.PAPER_J`)
_SUBPACKAGES = frozenset(
    "_runtime capture cli controls design gaits identify model montecarlo paper planning plots solve".split()
)

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    module = _WHERE.get(name)
    if module is None and name not in _SUBPACKAGES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if module is None:
        return _importlib.import_module(f".{name}", __name__)
    mod = _importlib.import_module(f".{module}", __name__)
    for other in _EXPORTS[module]:  # the module's other names come with it
        globals()[other] = getattr(mod, other)
    return globals()[name]


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
