"""The package's one constrained nonlinear solver: IPOPT (through `cyipopt`) on a sparse problem
whose values and derivatives the caller computes (with JAX):

    minimise f(z)  subject to  lb <= z <= ub,  cl <= g(z) <= cu

`SparseProblem` holds the callables IPOPT asks for (objective, gradient, constraints, the
constraint Jacobian's and the Lagrangian Hessian's values on a fixed sparsity structure);
`minimise` runs IPOPT from a start point and returns an `IpoptResult` with a named status. An
infinite bound is no bound. Used by the direct planner (`jsphere.planning.direct`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

#: IPOPT's return codes (`ApplicationReturnStatus`) by name; `solved` and `acceptable` are success
STATUS = {
    0: "solved",
    1: "acceptable",
    2: "infeasible",
    3: "search_direction_too_small",
    4: "diverging",
    5: "stopped_by_user",
    6: "feasible_point_found",
    -1: "max_iterations",
    -2: "restoration_failed",
    -3: "error_in_step_computation",
    -4: "max_cpu_time",
    -10: "not_enough_degrees_of_freedom",
    -11: "invalid_problem_definition",
    -12: "invalid_option",
    -13: "invalid_number_detected",
}
SUCCESS = ("solved", "acceptable")
#: what IPOPT reads as an infinite bound
INF = 1e20


@dataclasses.dataclass(frozen=True)
class SparseProblem:
    """The callables of an NLP on `n` variables and `m` constraints, each of a NumPy vector `z`:
    `objective(z) -> float`, `gradient(z) -> (n,)`, `constraints(z) -> (m,)`,
    `jacobian(z) -> values` on `jacobian_structure = (rows, cols)`, and
    `hessian(z, lam, sigma) -> values` of `sigma f + lam . g` on `hessian_structure` (its lower
    triangle, each position once)."""

    objective: Callable
    gradient: Callable
    constraints: Callable
    jacobian: Callable
    jacobian_structure: tuple[np.ndarray, np.ndarray]
    hessian: Callable
    hessian_structure: tuple[np.ndarray, np.ndarray]


@dataclasses.dataclass(frozen=True)
class IpoptResult:
    """`z`: the last iterate; `status`: a name of `STATUS`; `iterations`; `objective`;
    `constraint_violation` (the largest, unscaled); `multipliers` of the constraints."""

    z: np.ndarray
    status: str
    iterations: int
    objective: float
    constraint_violation: float
    multipliers: np.ndarray

    @property
    def success(self) -> bool:
        return self.status in SUCCESS


class _Adapter:
    """The object `cyipopt.Problem` calls; counts iterations and reports them."""

    def __init__(self, problem: SparseProblem, on_iteration: Callable[[int, float, float], None] | None):
        self.p = problem
        self.on_iteration = on_iteration
        self.iterations = 0
        self.violation = math.inf

    def objective(self, z):
        return float(self.p.objective(z))

    def gradient(self, z):
        return np.asarray(self.p.gradient(z), float)

    def constraints(self, z):
        return np.asarray(self.p.constraints(z), float)

    def jacobian(self, z):
        return np.asarray(self.p.jacobian(z), float)

    def jacobianstructure(self):
        return self.p.jacobian_structure

    def hessian(self, z, lam, sigma):
        return np.asarray(self.p.hessian(z, lam, sigma), float)

    def hessianstructure(self):
        return self.p.hessian_structure

    def intermediate(self, alg_mod, iter_count, obj_value, inf_pr, inf_du, mu, d_norm, *rest):
        self.iterations = int(iter_count)
        self.violation = float(inf_pr)
        if self.on_iteration is not None:
            self.on_iteration(int(iter_count), float(obj_value), float(inf_pr))
        return True


def minimise(
    problem: SparseProblem,
    z0: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    constraint_bounds: tuple[np.ndarray, np.ndarray],
    *,
    tol: float = 1e-8,
    max_iter: int = 500,
    on_iteration: Callable[[int, float, float], None] | None = None,
    options: dict | None = None,
) -> IpoptResult:
    """IPOPT (MUMPS, adaptive barrier) from `z0`; `on_iteration(k, f, violation)` after each
    iteration; `options`: IPOPT's options over these. Never raises on a failed solve: the
    result's `status` says what happened."""
    import cyipopt

    lb, ub = (np.clip(np.asarray(b, float), -INF, INF) for b in bounds)
    cl, cu = (np.clip(np.asarray(b, float), -INF, INF) for b in constraint_bounds)
    ad = _Adapter(problem, on_iteration)
    nlp = cyipopt.Problem(n=len(z0), m=len(cl), problem_obj=ad, lb=lb, ub=ub, cl=cl, cu=cu)
    for k, v in (
        ("print_level", 0),
        ("sb", "yes"),
        ("tol", float(tol)),
        ("max_iter", int(max_iter)),
        ("mu_strategy", "adaptive"),
        ("linear_solver", "mumps"),
        *(options or {}).items(),
    ):
        nlp.add_option(k, v)
    z, info = nlp.solve(np.asarray(z0, float))
    return IpoptResult(
        z=np.asarray(z, float),
        status=STATUS.get(int(info["status"]), f"status {info['status']}"),
        iterations=ad.iterations,
        objective=float(info["obj_val"]),
        constraint_violation=ad.violation,
        multipliers=np.asarray(info["mult_g"], float),
    )
